"""Live operator view: frame sources, adaptive exposure, previews and a browser ground station (``pihim live``)."""
