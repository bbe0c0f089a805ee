"""``pihim polar`` (stub)."""


def polar() -> None:
    """Raw frames to Stokes, DoLP and AoP."""
    raise NotImplementedError
