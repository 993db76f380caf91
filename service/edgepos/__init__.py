"""edgepos: an edge positioning service for connected vehicles."""

__version__ = "0.1.0"
