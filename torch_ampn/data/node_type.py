"""Node types of a stamp-forming graph (one-hot encoded as node features)."""

from __future__ import annotations

from enum import IntEnum


class NodeType(IntEnum):
    """Kind of a mesh node.

    ``PLY`` nodes are free and predicted by the model; ``PUNCH`` and ``DIE`` nodes belong
    to rigid tools that follow a prescribed motion.
    """

    PLY = 0
    PUNCH = 1
    DIE = 2

    @classmethod
    def count(cls) -> int:
        """Number of node types (length of the one-hot encoding)."""
        return len(cls)
