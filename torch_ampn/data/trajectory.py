"""Trajectory: one forming simulation (meshes, node data and positions per saved step).

File format (``.pt``, one trajectory per file, written atomically, read with
``torch.load(weights_only=True)``): a ``dict`` with

=================  ====================  =====================================================
key                type / shape          meaning
=================  ====================  =====================================================
``format``         ``str``               ``"torch-ampn-trajectory"``
``version``        ``int``               format version (1)
``pos``            float ``[T+1, N, 3]``  node positions at the saved steps, mm
``time``           float ``[T+1]``        time of each saved step, s
``cells``          list of long          one ``[F_c, 3]`` (triangles) or ``[F_c, 4]`` (quads)
                   ``[F_c, k]``          tensor per component, global node indices
``component``      long ``[N]``           component id ``0 .. C-1`` of every node
``node_type``      long ``[N]``           :class:`~torch_ampn.data.NodeType` of every node
``fiber``          float ``[N, 3]``       unit fibre direction in the initial state (ply nodes;
                                         zero on tool nodes)
``names``          list of ``str``       component names (length ``C``)
``gripper_nodes``  long ``[G, P]``        the node gripped by gripper ``g`` in each of the
                                         ``P`` plies (a needle through the stack)
``gripper_anchor`` float ``[G, 3]``       space-fixed anchor each gripper pulls towards, mm
``gripper_force``  float ``[G]``          pulling force magnitude, N
``meta``           ``dict``              free-form: simulator settings, seed, ...
=================  ====================  =====================================================

Tool nodes (``node_type != PLY``) follow a prescribed motion, which is their ``pos``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.utils.io import atomic_torch_save, load_torch_file

FORMAT_NAME = "torch-ampn-trajectory"
FORMAT_VERSION = 1


def gripper_points(pos: Tensor, gripper_nodes: Tensor) -> Tensor:
    """Gripping points: the mean position of each gripper's nodes (one per ply), ``[..., G, 3]``.

    Args:
        pos: Node positions ``[..., N, 3]`` (e.g. ``[T+1, N, 3]`` or one step ``[N, 3]``).
        gripper_nodes: The gripped nodes ``LongTensor[..., G, P]`` (rows of ``pos``'s node axis;
            a batch of ``B`` graphs stacked along the node axis passes ``[B, G, P]``).
    """
    return pos[..., gripper_nodes, :].mean(-2)


def gripper_forces(points: Tensor, anchor: Tensor, magnitude: Tensor) -> Tensor:
    """Force of every gripper, ``magnitude`` N from its point towards its anchor, ``[..., G, 3]``.

    Args:
        points: Gripping points ``[..., G, 3]`` (:func:`gripper_points`).
        anchor: Space-fixed anchors ``[G, 3]`` (or ``[B, G, 3]``), broadcast against ``points``.
        magnitude: Force magnitudes ``[G]`` (or ``[B, G]``), N.
    """
    d = anchor - points  # [..., G, 3]
    return magnitude[..., None] * d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


class TrajectoryFormatError(ValueError):
    """A trajectory file or object is invalid; the message names the file and the field."""


@dataclass
class Trajectory:
    """One simulated (or imported) forming trajectory. See the module docstring for fields."""

    pos: Tensor  # [T+1, N, 3]
    time: Tensor  # [T+1]
    cells: list[Tensor]  # C x [F_c, 3|4]
    component: Tensor  # [N]
    node_type: Tensor  # [N]
    fiber: Tensor  # [N, 3]
    names: list[str]
    gripper_nodes: Tensor  # [G, P]
    gripper_anchor: Tensor  # [G, 3]
    gripper_force: Tensor  # [G]
    meta: dict[str, Any] = field(default_factory=dict)
    #: Optional prior prediction of the positions ``[T+1, N, 3]`` (e.g. a setting-aware baseline's
    #: trajectory for these settings, :mod:`torch_ampn.baselines.prior`), an input of models with
    #: ``prior_features``; derived, never written to the file.
    prior: Tensor | None = field(default=None, repr=False)

    # ---- sizes -----------------------------------------------------------------------
    @property
    def num_steps(self) -> int:
        """Number of steps ``T`` (there are ``T + 1`` saved states)."""
        return self.pos.size(0) - 1

    @property
    def num_nodes(self) -> int:
        """Number of nodes ``N``."""
        return self.pos.size(1)

    @property
    def num_components(self) -> int:
        """Number of components ``C``."""
        return len(self.cells)

    @property
    def num_grippers(self) -> int:
        """Number of grippers ``G``."""
        return self.gripper_force.numel()

    # ---- derived quantities ----------------------------------------------------------
    @property
    def ply_mask(self) -> Tensor:
        """``BoolTensor[N]``: nodes whose motion is predicted (plies)."""
        return self.node_type == NodeType.PLY

    def displacement(self) -> Tensor:
        """Displacements from the initial state, ``[T+1, N, 3]``."""
        return self.pos - self.pos[:1]

    def edge_index(self) -> Tensor:
        """Undirected mesh edges of all components, ``LongTensor[2, E]``, both directions."""
        from torch_ampn.data.mesh import cells_to_edge_index

        return torch.cat([cells_to_edge_index(c, self.num_nodes) for c in self.cells], 1)

    def gripper_positions(self) -> Tensor:
        """Gripping points (mean over the plies' gripped nodes) at every saved step, ``[T+1, G, 3]``."""
        return gripper_points(self.pos, self.gripper_nodes)

    def gripper_force_vectors(self) -> Tensor:
        """Force of every gripper at every step, pointing at its anchor, ``[T+1, G, 3]``."""
        return gripper_forces(self.gripper_positions(), self.gripper_anchor, self.gripper_force)

    def to(self, device: torch.device | str) -> Trajectory:
        """A copy with every tensor on ``device`` (shares storage where it is already there)."""
        moved = {f: getattr(self, f) for f in _FIELDS}
        moved = {f: v.to(device) if isinstance(v, Tensor) else v for f, v in moved.items()}
        moved["cells"] = [c.to(device) for c in self.cells]
        prior = None if self.prior is None else self.prior.to(device)
        return Trajectory(**moved, meta=dict(self.meta), prior=prior)

    # ---- files -----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The file representation (see the module docstring)."""
        return dict(
            format=FORMAT_NAME,
            version=FORMAT_VERSION,
            pos=self.pos,
            time=self.time,
            cells=list(self.cells),
            component=self.component,
            node_type=self.node_type,
            fiber=self.fiber,
            names=list(self.names),
            gripper_nodes=self.gripper_nodes,
            gripper_anchor=self.gripper_anchor,
            gripper_force=self.gripper_force,
            meta=dict(self.meta),
        )

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "<dict>") -> Trajectory:
        """Build and validate a trajectory from :meth:`to_dict`'s form; ``source`` names it in errors."""
        if not isinstance(d, dict):
            raise TrajectoryFormatError(f"{source}: expected a dict, got {type(d).__name__}")
        if d.get("format") != FORMAT_NAME:
            raise TrajectoryFormatError(
                f"{source}: field 'format' must be {FORMAT_NAME!r}, got {d.get('format')!r}"
            )
        if d.get("version") != FORMAT_VERSION:
            raise TrajectoryFormatError(f"{source}: unsupported field 'version' {d.get('version')!r}")
        names = [f for f in _FIELDS if f not in d]
        if names:
            raise TrajectoryFormatError(f"{source}: missing field(s) {', '.join(repr(n) for n in names)}")
        traj = cls(**{f: d[f] for f in _FIELDS}, meta=dict(d.get("meta", {})))
        traj.validate(source)
        return traj

    def save(self, path: str | os.PathLike) -> None:
        """Validate, then write to ``path`` atomically (temporary file + rename)."""
        self.validate(str(path))
        atomic_torch_save(self.to_dict(), path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Trajectory:
        """Read and validate a trajectory file; errors name the file and the field."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such trajectory file")
        try:
            d = load_torch_file(path, "trajectory file")
        except ValueError as err:
            raise TrajectoryFormatError(str(err)) from None
        return cls.from_dict(d, str(path))

    # ---- validation ------------------------------------------------------------------
    def validate(self, source: str = "<trajectory>") -> None:
        """Raise :class:`TrajectoryFormatError` naming ``source`` and the field if anything is off."""

        def fail(name: str, msg: str) -> None:
            raise TrajectoryFormatError(f"{source}: field {name!r} {msg}")

        def tensor(name: str, value: Any, dims: int, floating: bool) -> None:
            if not isinstance(value, Tensor):
                fail(name, f"must be a tensor, got {type(value).__name__}")
            if value.dim() != dims:
                fail(name, f"must have {dims} dimensions, got shape {list(value.shape)}")
            if floating and not value.is_floating_point():
                fail(name, f"must be floating point, got {value.dtype}")
            if not floating and value.dtype not in (torch.int32, torch.int64):
                fail(name, f"must be an integer tensor, got {value.dtype}")
            if floating and not torch.isfinite(value).all():
                fail(name, "contains NaN or infinite values")

        tensor("pos", self.pos, 3, True)
        if self.pos.size(0) < 2 or self.pos.size(2) != 3:
            fail("pos", f"must have shape [T+1 >= 2, N, 3], got {list(self.pos.shape)}")
        n = self.pos.size(1)
        tensor("time", self.time, 1, True)
        if self.time.numel() != self.pos.size(0):
            fail("time", f"has {self.time.numel()} steps but 'pos' has {self.pos.size(0)}")
        if (self.time[1:] <= self.time[:-1]).any():
            fail("time", "must be strictly increasing")
        for name, value in (("component", self.component), ("node_type", self.node_type)):
            tensor(name, value, 1, False)
            if value.numel() != n:
                fail(name, f"has {value.numel()} entries but 'pos' has {n} nodes")
            if (value < 0).any():
                fail(name, "contains negative values")
        if int(self.node_type.max()) >= NodeType.count():
            fail("node_type", f"contains unknown type {int(self.node_type.max())}")
        tensor("fiber", self.fiber, 2, True)
        if tuple(self.fiber.shape) != (n, 3):
            fail("fiber", f"must have shape [{n}, 3], got {list(self.fiber.shape)}")
        if not isinstance(self.cells, (list, tuple)) or not self.cells:
            fail("cells", "must be a non-empty list with one tensor per component")
        if not isinstance(self.names, (list, tuple)) or len(self.names) != len(self.cells):
            fail("names", f"must list one name per component ({len(self.cells)})")
        num_comp = len(self.cells)
        counts = torch.bincount(self.component.long(), minlength=num_comp)
        if counts.numel() > num_comp:
            fail("component", f"has ids up to {counts.numel() - 1} but there are {num_comp} components")
        for c, cells in enumerate(self.cells):
            name = f"cells[{c}]"
            tensor(name, cells, 2, False)
            if cells.size(1) not in (3, 4) or cells.size(0) == 0:
                fail(name, f"must have shape [F > 0, 3 or 4], got {list(cells.shape)}")
            if int(cells.min()) < 0 or int(cells.max()) >= n:
                fail(name, f"references nodes outside 0..{n - 1}")
            if counts[c] == 0:
                fail("component", f"component {c} ({self.names[c]!r}) has no nodes")
            if (self.component[cells.reshape(-1)] != c).any():
                fail(name, f"references nodes of another component than {c}")
        tensor("gripper_nodes", self.gripper_nodes, 2, False)
        g = self.gripper_nodes.size(0)
        if g and (int(self.gripper_nodes.min()) < 0 or int(self.gripper_nodes.max()) >= n):
            fail("gripper_nodes", f"references nodes outside 0..{n - 1}")
        if g and (self.node_type[self.gripper_nodes] != NodeType.PLY).any():
            fail("gripper_nodes", "must reference ply nodes")
        tensor("gripper_anchor", self.gripper_anchor, 2, True)
        if tuple(self.gripper_anchor.shape) != (g, 3):
            fail("gripper_anchor", f"must have shape [{g}, 3], got {list(self.gripper_anchor.shape)}")
        tensor("gripper_force", self.gripper_force, 1, True)
        if self.gripper_force.numel() != g:
            fail("gripper_force", f"must have {g} entries, got {self.gripper_force.numel()}")
        if not isinstance(self.meta, dict):
            fail("meta", f"must be a dict, got {type(self.meta).__name__}")


_FIELDS = (
    "pos",
    "time",
    "cells",
    "component",
    "node_type",
    "fiber",
    "names",
    "gripper_nodes",
    "gripper_anchor",
    "gripper_force",
)
