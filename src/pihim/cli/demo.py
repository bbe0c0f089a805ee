"""``pihim demo`` (stub)."""


def demo() -> None:
    """Run the main job on the embedded default."""
    raise NotImplementedError
