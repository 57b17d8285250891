"""The warehouse the team works in: its geometry and its knowledge bases."""

from .warehouse import Layout, Position, layout_from_row

__all__ = ["Layout", "Position", "layout_from_row"]
