"""Datasets: whole trajectories of a split, and (t-1, t) training windows as ``HierarchicalData``."""

from __future__ import annotations

import copy
import hashlib
import os
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory
from torch_ampn.hierarchy.amg import build_hierarchy
from torch_ampn.hierarchy.hierarchical_data import HierarchicalData, level_name

SPLITS = ("train", "val", "test")


def split_files(root: str | os.PathLike, split: str) -> list[Path]:
    """Trajectory files of ``split`` (``<root>/<split>/*.pt``, sorted by name)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return sorted((Path(root) / split).glob("*.pt"))


def check_dataset(root: str | os.PathLike) -> tuple[list[dict[str, object]], list[str]]:
    """Load every trajectory of a dataset folder and summarise it per split.

    Returns:
        ``(rows, problems)``: one row per split with ``split``, ``files``, ``nodes``,
        ``steps`` and ``topologies`` (distinct meshes, by :func:`topology_key`), and one line
        per problem: a file that does not load (naming the file and the field), a dataset
        without trajectories, a split with more than one mesh (one hierarchy per split is what
        the training expects; the line lists the files of each mesh).
    """
    rows: list[dict[str, object]] = []
    problems: list[str] = []
    for split in SPLITS:
        files = split_files(root, split)
        meshes: dict[str, list[str]] = {}
        nodes: set[int] = set()
        steps: set[int] = set()
        for path in files:
            try:
                traj = Trajectory.load(path)
            except (OSError, ValueError) as err:  # TrajectoryFormatError is a ValueError
                problems.append(" ".join(str(err).split()) if str(path) in str(err) else f"{path}: {err}")
                continue
            meshes.setdefault(topology_key(traj), []).append(path.name)
            nodes.add(traj.num_nodes)
            steps.add(traj.num_steps)
        if len(meshes) > 1:
            groups = "; ".join(f"{len(names)} like {names[0]}" for names in meshes.values())
            problems.append(f"{Path(root) / split}: {len(meshes)} different meshes ({groups})")
        summary = dict(nodes=sorted(nodes), steps=sorted(steps), topologies=len(meshes))
        rows.append(dict(split=split, files=len(files), **summary))
    if not any(row["files"] for row in rows):
        problems.append(f"{root}: no trajectory files in train/, val/ or test/")
    return rows, problems


class TrajectoryDataset:
    """The trajectories of one split, loaded (and validated) on first access and kept in memory.

    At most ``max_cached_mb`` of trajectories are kept (the least recently used go first), so
    a large dataset (the paper's 684 training trajectories at its resolution are about 7 GB)
    is read from disk as needed instead of filling the memory.

    Args:
        root: Dataset folder with ``train/``, ``val/``, ``test/`` sub-folders.
        split: ``"train"``, ``"val"`` or ``"test"``.
        max_cached_mb: Memory for loaded trajectories in MB (their tensors); ``None``: no limit.
        priors: File stem -> prior ``[T+1, N, 3]``, set as each loaded trajectory's
            :attr:`~torch_ampn.data.Trajectory.prior` (:mod:`torch_ampn.baselines.prior`); ``None``: none.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str,
        max_cached_mb: float | None = 2048.0,
        priors: Mapping[str, Tensor] | None = None,
    ) -> None:
        self.root, self.split = Path(root), split
        self.priors = priors
        self.files = split_files(root, split)
        if not self.files:
            raise FileNotFoundError(f"{self.root / split}: no trajectory files (*.pt)")
        self.max_cached_bytes = None if max_cached_mb is None else max_cached_mb * 1e6
        self._cache: OrderedDict[int, Trajectory] = OrderedDict()
        self._cached_bytes = 0

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> Trajectory:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        traj = Trajectory.load(self.files[i])
        if self.priors is not None:
            stem = self.files[i].stem
            if stem not in self.priors:
                raise KeyError(f"{self.files[i]}: no prior for this trajectory")
            traj.prior = self.priors[stem]
        self._cache[i] = traj
        self._cached_bytes += _tensor_bytes(traj)
        limit = self.max_cached_bytes
        while limit is not None and self._cached_bytes > limit and len(self._cache) > 1:
            _, dropped = self._cache.popitem(last=False)
            self._cached_bytes -= _tensor_bytes(dropped)
        return traj

    def __iter__(self) -> Iterator[Trajectory]:
        return (self[i] for i in range(len(self)))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.root}, split={self.split!r}, trajectories={len(self)})"


def _tensor_bytes(traj: Trajectory) -> int:
    """Bytes of a trajectory's tensors."""
    tensors = [v for v in vars(traj).values() if torch.is_tensor(v)] + list(traj.cells)
    return sum(t.numel() * t.element_size() for t in tensors)


def topology_key(traj: Trajectory) -> str:
    """Hash of a trajectory's mesh topology (cells and node count)."""
    return _topology_hash(traj.num_nodes, traj.cells)


def _topology_hash(num_nodes: int, cells: list[Tensor]) -> str:
    h = hashlib.sha256(str(num_nodes).encode())
    for c in cells:
        h.update(c.long().contiguous().numpy().tobytes())
    return h.hexdigest()


def file_topology_key(path: str | os.PathLike) -> tuple[str, int]:
    """:func:`topology_key` and node count of a trajectory file, without reading its positions.

    The file is memory-mapped, so only its cells are read (a paper-resolution file holds
    about 10 MB of positions and 0.3 MB of cells). ``ValueError`` naming the file if it is
    not a trajectory file.
    """
    try:
        d = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        num_nodes, cells = int(d["pos"].shape[1]), list(d["cells"])
    except Exception as err:  # noqa: BLE001 - any unreadable file: one line naming it
        raise ValueError(f"{path}: not a readable trajectory file ({type(err).__name__})") from err
    return _topology_hash(num_nodes, cells), num_nodes


class HierarchyCache:
    """One AMG hierarchy per mesh topology, in memory and (optionally) on disk.

    Coarse levels also get ``node_type`` and ``component`` of their root nodes.
    """

    def __init__(self, cache_dir: str | os.PathLike | None = None, **hierarchy_kwargs) -> None:
        self.cache_dir = cache_dir
        self.kwargs = hierarchy_kwargs
        self._memory: dict[str, HierarchicalData] = {}

    def __call__(self, traj: Trajectory) -> HierarchicalData:
        """The hierarchy of ``traj``'s mesh (shared; copy it before adding fields)."""
        key = topology_key(traj)
        if key not in self._memory:
            h = build_hierarchy(traj.edge_index(), traj.num_nodes, cache_dir=self.cache_dir, **self.kwargs)
            for k in range(h.num_levels):
                idx = h.fine_index(k)
                h[level_name(k)].node_type = traj.node_type[idx]
                h[level_name(k)].component = traj.component[idx]
            self._memory[key] = h
        return self._memory[key]


def set_window(
    data: HierarchicalData,
    pos: Tensor,
    prev_disp: Tensor,
    next_disp: Tensor,
    ply_mask: Tensor,
    gripper_pos: Tensor,
    gripper_force: Tensor,
    prior_pos: Tensor | None = None,
    prior_next: Tensor | None = None,
) -> HierarchicalData:
    r"""Write the state fields of a window :math:`(t-1, t)` into ``data`` (in place) and return it.

    Used by :func:`step_sample` and by the pushforward of
    :class:`~torch_ampn.training.NextStepLightningModule`, which builds the window before.

    Args:
        data: The window's hierarchy (a shallow copy, or a batch).
        pos: :math:`x^{t-1}` ``[N, 3]``.
        prev_disp: :math:`x^{t-1} - x^{t-2}` ``[N, 3]``.
        next_disp: :math:`x^t - x^{t-1}` ``[N, 3]``: the target, and on tool nodes the prescribed
            motion; a bundled window (:func:`step_sample`'s ``bundle_steps`` ``B``) passes the
            offsets of the next ``B`` steps, ``[N, 3 B]``.
        ply_mask: ``BoolTensor[N]``: ply nodes (predicted); the others are tools.
        gripper_pos: Gripper positions at :math:`t-1` ``[B, G, 3]``.
        gripper_force: Gripper force vectors at :math:`t-1` ``[B, G, 3]``.
        prior_pos: The prior's positions :math:`p^{t-1}` ``[N, 3]`` (models with prior
            features; see :attr:`~torch_ampn.data.Trajectory.prior`), or ``None``.
        prior_next: The prior's positions :math:`p^t` ``[N, 3]``, or ``None``.
    """
    l0 = data["l0"]
    if prior_pos is not None and prior_next is not None:
        l0.prior_pos = prior_pos
        l0.prior_next = prior_next
    l0.pos = pos
    l0.prev_disp = prev_disp
    l0.bc_disp = torch.where(ply_mask[:, None], torch.zeros_like(next_disp), next_disp)
    l0.target = next_disp
    l0.ply_mask = ply_mask
    data.gripper_pos = gripper_pos
    data.gripper_force = gripper_force
    return data


def step_sample(
    traj: Trajectory, t: int, hierarchy: HierarchicalData, bundle_steps: int = 1
) -> HierarchicalData:
    r"""The training window ``(t-1, t)`` of ``traj`` on ``hierarchy`` (which is not modified).

    With ``bundle_steps`` :math:`B > 1` (temporal bundling: one call predicts the next ``B``
    saved steps), ``bc_disp`` and ``target`` are ``[N, 3 B]``: the offsets
    :math:`x^{t-1+k} - x^{t-1}` for :math:`k = 1 .. B`, column block ``k - 1``; steps past the
    trajectory's last repeat its last state (so the offsets stay constant there).

    Fine level (``l0``) fields, ``N`` nodes:

    * ``pos0`` ``[N, 3]``: initial positions; ``pos`` ``[N, 3]``: positions :math:`x^{t-1}`;
    * ``prev_disp`` ``[N, 3]``: previous residual :math:`x^{t-1} - x^{t-2}` (zero at ``t = 1``);
    * ``prev_prev_disp`` ``[N, 3]``: the residual before, :math:`x^{t-2} - x^{t-3}` (zero for
      ``t < 3``), which with ``prev_disp`` and the ``prev_gripper_*`` fields makes the
      window ``(t-2, t-1)`` (the pushforward training of
      :class:`~torch_ampn.training.NextStepLightningModule`);
    * ``bc_disp`` ``[N, 3]``: prescribed tool motion :math:`x^t - x^{t-1}` on tool nodes, zero on plies
      (``[N, 3 B]`` when bundled);
    * ``target`` ``[N, 3]``: the residual :math:`\Delta u^t = x^t - x^{t-1}` (``[N, 3 B]`` when bundled);
    * ``fiber`` ``[N, 3]``, ``ply_mask`` ``[N]``, and ``node_type``/``component`` on every level;
    * where ``traj.prior`` is set: ``prior_pos``, ``prior_next`` and ``prior_before`` ``[N, 3]``,
      the prior's positions :math:`p^{t-1}`, :math:`p^t` and :math:`p^{\max(t-2, 0)}`.

    Graph level: ``gripper_pos`` and ``gripper_force`` ``[1, G, 3]`` at :math:`t-1`,
    ``prev_gripper_pos`` and ``prev_gripper_force`` at :math:`\max(t-2, 0)`,
    ``step`` ``[1]`` (= t) and ``traj_index`` is left to the caller.
    """
    if not 1 <= t <= traj.num_steps:
        raise IndexError(f"step {t} out of range 1..{traj.num_steps}")
    if bundle_steps < 1:
        raise ValueError(f"bundle_steps must be >= 1, got {bundle_steps}")
    x_prev = traj.pos[t - 1]
    ahead = [min(t - 1 + k, traj.num_steps) for k in range(1, bundle_steps + 1)]
    next_disp = torch.cat([traj.pos[s] - x_prev for s in ahead], dim=-1)  # [N, 3 B]
    gripper_pos, gripper_force = traj.gripper_positions(), traj.gripper_force_vectors()  # [T+1, G, 3]
    prior = traj.prior  # [T+1, N, 3] or None
    data = set_window(
        copy.copy(hierarchy),
        pos=x_prev,
        prev_disp=x_prev - traj.pos[t - 2] if t >= 2 else torch.zeros_like(x_prev),
        next_disp=next_disp,
        ply_mask=traj.node_type == NodeType.PLY,
        gripper_pos=gripper_pos[t - 1][None],
        gripper_force=gripper_force[t - 1][None],
        prior_pos=None if prior is None else prior[t - 1],
        prior_next=None if prior is None else prior[t],
    )
    l0 = data["l0"]
    if prior is not None:
        l0.prior_before = prior[max(t - 2, 0)]
    l0.pos0 = traj.pos[0]
    l0.prev_prev_disp = traj.pos[t - 2] - traj.pos[t - 3] if t >= 3 else torch.zeros_like(x_prev)
    l0.fiber = traj.fiber
    data.prev_gripper_pos = gripper_pos[max(t - 2, 0)][None]
    data.prev_gripper_force = gripper_force[max(t - 2, 0)][None]
    data.step = torch.tensor([t])
    return data


class StepDataset(torch.utils.data.Dataset):
    """All ``(t-1, t)`` windows of a split as :class:`HierarchicalData` samples (see :func:`step_sample`).

    Sample ``i`` is trajectory ``i // T`` at step ``i % T + 1``. Batches with PyG's
    ``DataLoader``. The hierarchy is built once per mesh topology and cached (in memory and,
    with ``cache_dir``, on disk).

    Args:
        root: Dataset folder.
        split: ``"train"``, ``"val"`` or ``"test"``.
        cache_dir: Folder for hierarchy files (default ``<root>/cache``; ``None`` disables disk caching).
        max_levels: Passed to :func:`build_hierarchy`.
        min_coarse_nodes: Passed to :func:`build_hierarchy`.
        transform: Applied to every sample (e.g. :class:`~torch_ampn.transforms.ComponentRadiusGraph`).
        cache_samples: Keep every (transformed) sample in memory after its first use, so that
            later epochs skip building it and its contact edges again. Only for deterministic
            transforms; costs the per-window tensors (positions, residuals, contact edges) of
            the whole split, about 60 kB per window of the coarse default mesh. The samples
            handed out are the cached objects: replace their tensors rather than writing into
            them (a batched sample is a new object anyway).
        max_cached_mb: Memory for loaded trajectories (see :class:`TrajectoryDataset`).
        priors: Priors of the trajectories (see :class:`TrajectoryDataset`).
        bundle_steps: Steps every window's target spans (temporal bundling; see :func:`step_sample`).
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str = "train",
        cache_dir: str | os.PathLike | None = "default",
        max_levels: int = 4,
        min_coarse_nodes: int = 16,
        transform: Callable[[HierarchicalData], HierarchicalData] | None = None,
        cache_samples: bool = False,
        max_cached_mb: float | None = 2048.0,
        priors: Mapping[str, Tensor] | None = None,
        bundle_steps: int = 1,
    ) -> None:
        if bundle_steps < 1:
            raise ValueError(f"bundle_steps must be >= 1, got {bundle_steps}")
        self.bundle_steps = bundle_steps
        self.transform = transform
        self.cache_samples = cache_samples
        self._samples: dict[int, HierarchicalData] = {}
        self.trajectories = TrajectoryDataset(root, split, max_cached_mb=max_cached_mb, priors=priors)
        cache = Path(root) / "cache" if cache_dir == "default" else cache_dir
        self.hierarchies = HierarchyCache(cache, max_levels=max_levels, min_coarse_nodes=min_coarse_nodes)
        self.steps = [self.trajectories[i].num_steps for i in range(len(self.trajectories))]
        self.offsets = torch.tensor([0, *self.steps]).cumsum(0)

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def index(self, i: int) -> tuple[int, int]:
        """``(trajectory index, step t)`` of sample ``i``."""
        if not 0 <= i < len(self):
            raise IndexError(f"sample {i} out of range for {len(self)} samples")
        j = int(torch.searchsorted(self.offsets, torch.tensor(i), right=True)) - 1
        return j, i - int(self.offsets[j]) + 1

    def sample(self, traj: Trajectory, t: int) -> HierarchicalData:
        """The sample of ``traj`` at step ``t`` (:func:`step_sample`), before the transform."""
        return step_sample(traj, t, self.hierarchies(traj), self.bundle_steps)

    def __getitem__(self, i: int) -> HierarchicalData:
        if i in self._samples:
            return self._samples[i]
        j, t = self.index(i)
        data = self.sample(self.trajectories[j], t)
        data.traj_index = torch.tensor([j])
        if self.transform is not None:
            data = self.transform(data)
        if self.cache_samples:
            self._samples[i] = data
        return data


def direct_sample(traj: Trajectory, hierarchy: HierarchicalData, targets: bool = True) -> HierarchicalData:
    """The initial state of ``traj`` as a direct model's sample: the window at ``t = 1`` and every target.

    The fields of :func:`step_sample` at ``t = 1`` (initial positions, no previous motion, the
    grippers at :math:`t = 0`), and ``l0.displacement`` ``[N, T, 3]``: :math:`x^t - x^0` of every
    saved step ``t = 1..T`` (float32), the target of
    :class:`~torch_ampn.forming.direct.DirectSurrogate`. Where ``traj.prior`` is set, also
    ``l0.prior_displacement`` ``[N, T, 3]``: the prior's :math:`p^t - x^0` (what a direct model
    with ``base="prior"`` departs from). ``targets=False`` leaves ``displacement`` out: the
    trajectory's future is then never read (a prediction's input).
    """
    data = step_sample(traj, 1, hierarchy)
    x0 = traj.pos[0]
    if targets:
        data["l0"].displacement = (traj.pos[1:] - x0).transpose(0, 1).float().contiguous()
    if traj.prior is not None:
        data["l0"].prior_displacement = (traj.prior[1:] - x0).transpose(0, 1).float().contiguous()
    return data


class DirectDataset(StepDataset):
    """One :func:`direct_sample` per trajectory of a split (arguments as :class:`StepDataset`).

    Sample ``i`` is trajectory ``i`` (all its steps at once); batches with PyG's ``DataLoader``
    when the trajectories have the same step count.
    """

    def __len__(self) -> int:
        return len(self.trajectories)

    def index(self, i: int) -> tuple[int, int]:
        """``(trajectory index, 1)``: sample ``i`` is trajectory ``i`` from its first window."""
        if not 0 <= i < len(self):
            raise IndexError(f"sample {i} out of range for {len(self)} trajectories")
        return i, 1

    def sample(self, traj: Trajectory, t: int) -> HierarchicalData:
        """The whole trajectory from its initial state (:func:`direct_sample`), before the transform."""
        return direct_sample(traj, self.hierarchies(traj))
