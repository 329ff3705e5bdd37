r"""A fast rollout of an :class:`~torch_ampn.forming.AMPNSurrogate`: static shapes, compiled, batched.

:func:`~torch_ampn.rollout.rollout` rebuilds a :class:`~torch_ampn.data.HierarchicalData` window,
searches the contact edges and builds the features with many small eager operations every
step. :class:`FastRollout` does the same arithmetic with fixed shapes:

* everything that does not change during a rollout (mesh, down and up edges with their
  offsets for ``B`` settings and their aggregation tables, node types, components, fibres) is
  built once; the features, their normalisation and the position update are the plain path's
  own functions (:func:`~torch_ampn.forming.step_features`, ``AMPNSurrogate.normalize``,
  :func:`~torch_ampn.rollout.plain.next_positions`);
* the contact edges of every level are those of
  :func:`~torch_ampn.transforms.component_radius_table`: on small levels every slot of its
  fixed-size table (with a validity mask), selected inside the compiled step from candidates
  kept between steps (:class:`~torch_ampn.transforms.candidates.ContactCandidates`, which
  search again only when they cannot guarantee the exact table); on levels searched at every
  step the used slots, as an edge list padded to a slowly growing capacity;
* the step (contact selection, features, normalisation) and the network are compiled with
  ``torch.compile`` (static shapes) when ``compile=True``; where compiling fails (no C++
  compiler, an unsupported device) it warns once and runs the same code eagerly;
* ``B`` process settings of the same mesh (a design study) are rolled out as one batch.

The result equals :func:`~torch_ampn.rollout.rollout` with ``surrogate.predict_residual``
up to floating-point summation order (the same contact edges, features and noise draws; each
setting draws its noise from its own generator, so a batch equals its settings one by one).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from contextlib import nullcontext

import torch
from torch import Tensor

from torch_ampn.data.node_type import NodeType
from torch_ampn.data.trajectory import Trajectory, gripper_forces, gripper_points
from torch_ampn.forming.features import prior_features, step_features
from torch_ampn.forming.surrogate import AMPNSurrogate
from torch_ampn.hierarchy.hierarchical_data import CONTACT, DOWN, MESH, UP, HierarchicalData, edge_type
from torch_ampn.nn.slots import SlottedEdgeIndex
from torch_ampn.rollout.plain import next_positions
from torch_ampn.transforms.candidates import (
    CandidateState,
    ContactCandidates,
    DenseState,
    PatchState,
    select_table,
)
from torch_ampn.transforms.radius import component_radius_table
from torch_ampn.utils.compile_fallback import EagerFallback
from torch_ampn.utils.heap import retained_heap
from torch_ampn.utils.own_code import own_code
from torch_ampn.utils.threads import follow_free_cpu
from torch_ampn.utils.tuning import cpu_tuning_enabled


class FastPathUnavailable(ValueError):
    """The surrogate's settings have no fast path (e.g. plain-radius contact edges)."""


def fast_path_supported(surrogate: AMPNSurrogate) -> str | None:
    """``None`` if :class:`FastRollout` supports ``surrogate``, else the reason why not."""
    if surrogate.contact.mode != "component_knn":
        return f"contact mode {surrogate.contact.mode!r} has no fixed-size contact tables"
    if getattr(surrogate, "network_class", None) is not None:
        return f"network_class {surrogate.network_class!r} is not an AMPN"
    if getattr(surrogate, "prior_base", False):
        return "prior_base (the prior's step as the base of the prediction)"
    if getattr(surrogate, "bundle_steps", 1) > 1:
        return f"bundle_steps={surrogate.bundle_steps} (a model that predicts several steps per call)"
    return None


def _cpp_wrapper_from_environment() -> bool | None:
    """Inductor's ``TORCHINDUCTOR_CPP_WRAPPER`` (``"1"``: on, ``"0"``: off), ``None`` where unset."""
    value = os.environ.get("TORCHINDUCTOR_CPP_WRAPPER")
    if value is None or value.strip() == "":
        return None
    return value.strip() == "1"  # Inductor's own reading: anything but "1" is off


class FastRollout:
    r"""Rolls an :class:`~torch_ampn.forming.AMPNSurrogate` out over ``B`` settings of one mesh at once.

    Build it once per (surrogate, mesh, batch size); call it for every batch of trajectories
    of that mesh (compiled code is reused).

    Args:
        surrogate: The trained surrogate (its weights are read at every call, not copied).
        hierarchy: The mesh's hierarchy (e.g. from :class:`~torch_ampn.data.HierarchyCache`).
        batch_size: ``B``, settings per call.
        compile: Compile the step and the network (``torch.compile``, static shapes).
        device: Where to run (default: the surrogate's device).
        candidates: ``mode`` of :class:`~torch_ampn.transforms.candidates.ContactCandidates`
            (``"auto"``, ``"dense"``, ``"patches"``, ``"verlet"`` or ``"search"``), or one per level.
        skin: Verlet skin (default: the level's radius).
        capacity: Verlet candidates per (node, other component) (default ``2 k + 2``).
        retain_heap: On the CPU, keep freed memory in the process heap while a rollout runs
            (:func:`torch_ampn.utils.heap.retained_heap`, glibc only), so that the step's buffers
            are not faulted in afresh at every step. It changes glibc's settings for the whole
            process, so ``None`` (default) does it only where the process turned the CPU tuning on
            (:func:`torch_ampn.utils.tuning.enable_cpu_tuning`: the command-line programs do).
        cpp_wrapper: On the CPU, let Inductor write the compiled step's wrapper in C++, so
            that its kernel calls are not made from Python. ``None`` (default): where the
            step is bound by calls rather than arithmetic, ``B N d <=`` :attr:`CPP_WRAPPER_LIMIT`
            (the quickstart model on the coarse mesh, not the paper's network on its mesh,
            whose C++ wrapper took 11 minutes to compile on 2 cores for ~1 % of a step),
            unless Inductor's environment variable ``TORCHINDUCTOR_CPP_WRAPPER`` is set
            (``1``: always, ``0``: never; e.g. to save the wrapper's compile, about half a
            minute per mesh, where each mesh is rolled out only once).

    Example::

        fast = FastRollout(surrogate, hierarchy, batch_size=8)
        pred = fast(trajectories, generators)  # [8, T + 1, N, 3]
    """

    #: Largest ``B N d`` (settings x fine nodes x latent size) for which ``cpp_wrapper=None`` uses it.
    CPP_WRAPPER_LIMIT = 1 << 18

    def __init__(
        self,
        surrogate: AMPNSurrogate,
        hierarchy: HierarchicalData,
        batch_size: int = 1,
        compile: bool = True,
        device: torch.device | str | None = None,
        candidates: str | Sequence[str] = "auto",
        skin: float | None = None,
        capacity: int | None = None,
        retain_heap: bool | None = None,
        cpp_wrapper: bool | None = None,
    ) -> None:
        reason = fast_path_supported(surrogate)
        if reason is not None:
            raise FastPathUnavailable(f"no fast rollout: {reason}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.surrogate = surrogate
        self.batch_size = b = batch_size
        self.retain_heap = cpu_tuning_enabled() if retain_heap is None else bool(retain_heap)
        self.device = torch.device(device) if device is not None else next(surrogate.parameters()).device
        self.num_levels = surrogate.num_levels
        if hierarchy.num_levels < self.num_levels:
            raise ValueError(
                f"the model uses {self.num_levels} levels but the hierarchy has only {hierarchy.num_levels}"
            )
        self.source = hierarchy  # the caller's object (cache key); h is on the device
        h = (
            hierarchy.clone().to(self.device)
            if hierarchy.mesh(0).edge_index.device != self.device
            else hierarchy
        )
        self.hierarchy = h
        sizes = [h.level(k).num_nodes for k in range(self.num_levels)]  # N_k of one setting
        self.num_nodes = sizes[0]
        #: Elements of the step's typical kernel, ``B N d`` (what decides its C++ wrapper).
        self.elements = b * sizes[0] * getattr(surrogate.model, "hidden_channels", 1)
        dev = self.device
        graph = [torch.arange(b, device=dev).repeat_interleave(n) for n in sizes]  # [B N_k]

        def repeat_edges(index: Tensor, src: int, dst: int) -> Tensor:  # [2, E] -> [2, B E]
            shift = torch.arange(b, device=dev)[:, None]
            return torch.stack(
                [
                    (index[0][None] + shift * sizes[src]).reshape(-1),
                    (index[1][None] + shift * sizes[dst]).reshape(-1),
                ]
            )

        fine = h["l0"]
        self.batch0 = graph[0]
        self.node_type = fine.node_type.repeat(b)
        self.component = fine.component.repeat(b)
        self.ply = (fine.node_type == NodeType.PLY).repeat(b)  # [B N]
        shift = torch.arange(b, device=dev)[:, None] * sizes[0]
        self.fine_index = [torch.arange(b * sizes[0], device=dev)] + [
            (h.fine_index(k)[None] + shift).reshape(-1) for k in range(1, self.num_levels)
        ]  # level k -> rows of the batched l0
        self.level_component = [self.component[idx] for idx in self.fine_index]
        edges: dict[tuple, Tensor] = {}  # the fixed edge sets of B settings
        for k in range(self.num_levels):
            edges[edge_type(MESH, k)] = repeat_edges(h[edge_type(MESH, k)].edge_index, k, k)
            if k + 1 < self.num_levels:
                edges[edge_type(DOWN, k)] = repeat_edges(h[edge_type(DOWN, k)].edge_index, k, k + 1)
                edges[edge_type(UP, k)] = repeat_edges(h[edge_type(UP, k)].edge_index, k + 1, k)
        # with the aggregation tables of the fixed edge sets (dense reductions instead of scatters)
        self.edges = {
            key: SlottedEdgeIndex.build(index, b * sizes[int(key[2][1:])]) for key, index in edges.items()
        }
        s = surrogate
        contact = s.contact
        self.radius = [contact.level_radius(k) for k in range(self.num_levels)]
        self.k = contact.k
        self.initial_contact = contact.positions == "initial"  # ROBIN's edges, built once
        modes = [candidates] * self.num_levels if isinstance(candidates, str) else list(candidates)
        if len(modes) != self.num_levels:
            raise ValueError(
                f"candidates: expected one mode or {self.num_levels} (one per level), got {candidates!r}"
            )
        self.candidates = [
            ContactCandidates(
                self.level_component[k],
                self.radius[k],
                self.k,
                num_components=s.num_components,
                batch=graph[k],
                skin=skin,
                capacity=capacity,
                mode=modes[k],
            )
            for k in range(self.num_levels)
        ]
        self.contact_target = [
            torch.arange(b * n, device=dev).repeat_interleave(self.k * (s.num_components - 1)) for n in sizes
        ]
        self._static_contact: list[tuple[SlottedEdgeIndex, Tensor]] | None = None
        self._capacity = [0] * self.num_levels  # compacted contact edges per level (see _compact)
        self.cpp_wrapper = False
        # the step's callables: compiled where compile=True, each falling back to its eager code
        self._fallback = EagerFallback("the fast rollout runs eagerly")
        self._compile = compile
        self._stepped = False  # the first step compiles (see __call__)
        self._fused, self._inputs, self._network = self._step_fused, self._step_inputs, s.model
        if compile:
            # on CUDA the compiled graphs are captured as CUDA graphs and replayed (not yet measured)
            # on the CPU the bias additions go into the fused kernels (see compile_passes) and the
            # kernels are called from generated C++ where calls, not arithmetic, bound the step (~10 %)
            cuda = self.device.type == "cuda"
            if cpp_wrapper is None:
                cpp_wrapper = _cpp_wrapper_from_environment()
            if cpp_wrapper is None:
                cpp_wrapper = self.elements <= self.CPP_WRAPPER_LIMIT
            self.cpp_wrapper = bool(cpp_wrapper) and not cuda
            options = None
            if not cuda:
                from torch_ampn.utils.compile_passes import UnfuseBiasAdd  # Inductor's passes: when compiling

                options = {"post_grad_custom_post_pass": UnfuseBiasAdd(), "cpp_wrapper": self.cpp_wrapper}
            wrap = self._fallback.wrap
            if s.diffusion_steps == 1:  # the whole step in one graph
                fused = {"mode": "reduce-overhead"} if cuda else {"options": options}
                self._fused = wrap(
                    torch.compile(own_code(self._step_fused), dynamic=False, **fused), self._fused
                )
            else:  # K network calls per step: the inputs once, the network K times (no CUDA graphs:
                # a replay would overwrite the outputs of the other graph that are still in use)
                compiled = torch.compile(own_code(self._step_inputs), dynamic=False, options=options)
                self._inputs = wrap(compiled, self._inputs)
                compiled = torch.compile(own_code(s.model.forward), dynamic=False, options=options)
                self._network = wrap(compiled, self._network)

    @property
    def compiled(self) -> bool:
        """Whether the step runs compiled (``compile=True`` and no compiler failure so far)."""
        return self._compile and not self._fallback.failed

    # ---- one step ---------------------------------------------------------------------------
    def _step_inputs(
        self,
        pos: Tensor,
        prev: Tensor,
        tool_next: Tensor,
        gripper_nodes: Tensor,
        anchor: Tensor,
        magnitude: Tensor,
        fiber: Tensor,
        pos0: Tensor,
        prior_pos: Tensor | None,
        prior_next: Tensor | None,
        states: list[CandidateState | DenseState | PatchState | None],
        contact: list[tuple[SlottedEdgeIndex, Tensor] | None],
    ) -> tuple[dict, dict, dict, dict, Tensor, Tensor]:
        """A step's normalised features, edges (with slot tables), contact masks, previous residual, exact.

        The features are :func:`~torch_ampn.forming.features.step_features` normalised by
        :meth:`AMPNSurrogate.normalize <torch_ampn.forming.AMPNSurrogate.normalize>`, as on the plain
        path; what is this path's own is the contact tables' fixed shapes. The previous
        displacement is ``[B N, 3]``; the exactness flags (one per level) say whether the
        level's selected contact table is guaranteed exact. ``pos`` and ``prev`` are the
        positions ``[B N, 3]`` at steps ``t - 1`` and ``t - 2`` (``prev = pos`` at the first
        step), ``tool_next`` those at ``t`` with the tools on their path, ``pos0`` the initial
        ones; the grippers hold ply nodes (``gripper_nodes [B, G, m]``) and pull them towards
        ``anchor [B, G, 3]`` with force ``magnitude [B, G]``. Level ``k``'s contact edges are
        ``contact[k]`` (searched outside: edges with their slot table, validity) or else selected
        here from ``states[k]``. A model with prior features reads the prior's positions at
        ``t - 1`` and ``t`` (``prior_pos``, ``prior_next`` ``[B N, 3]``; else ``None``).
        """
        s = self.surrogate
        prev_disp = pos - prev  # [B N, 3]
        bc_disp = torch.where(self.ply[:, None], 0.0, tool_next - pos)  # [B N, 3]
        gripper_pos = gripper_points(pos, gripper_nodes)  # [B, G, 3]
        exact = []  # per level: the selected table is guaranteed exact
        index_dict, mask_dict = {}, {}  # edges with their aggregation tables, contact validity
        for k in range(self.num_levels):
            index_dict[edge_type(MESH, k)] = self.edges[edge_type(MESH, k)]
            key = edge_type(CONTACT, k)
            if contact[k] is not None:
                index_dict[key], mask_dict[key] = contact[k]
                exact.append(torch.ones((), dtype=torch.bool, device=pos.device))
            else:
                pos_k = pos if k == 0 else pos[self.fine_index[k]]  # [B N_k, 3]
                groups = self.candidates[k].num_groups
                nbr, mask, ok = select_table(pos_k, states[k], self.radius[k], self.k, groups)
                slot_ids = torch.arange(mask.numel(), device=mask.device).view(mask.shape)
                index = torch.stack([nbr.reshape(-1), self.contact_target[k]])  # every slot an edge
                table = torch.where(mask, slot_ids, -1)  # the table's own layout, masked slots left out
                index_dict[key] = SlottedEdgeIndex(index, table)
                mask_dict[key] = mask.reshape(-1)
                exact.append(ok)
            if k + 1 < self.num_levels:
                for key in (edge_type(DOWN, k), edge_type(UP, k)):
                    index_dict[key] = self.edges[key]
        x_dict, e_dict = s.normalize(
            *step_features(
                pos,
                pos0,
                prev_disp,
                bc_disp,
                self.node_type,
                self.component,
                fiber,
                gripper_pos,
                gripper_forces(gripper_pos, anchor, magnitude),
                self.fine_index[1:],
                {key: edges.edge_index for key, edges in index_dict.items()},
                s.num_components,
                batch=self.batch0,
                alpha=s.gripper_alpha,
                component_encoding=s.component_encoding,
                prior=None if prior_pos is None else prior_features(pos, prior_pos, prior_next),
            )
        )
        return x_dict, index_dict, e_dict, mask_dict, prev_disp, torch.stack(exact)

    def _step_fused(self, *args) -> tuple[Tensor, Tensor]:
        """One step of a ``K = 1`` model: ``(positions at t [B N, 3], exact per level)``.

        ``args`` as :meth:`_step_inputs`, with the noise list before ``states`` and ``contact``.
        """
        *inputs, noise, states, contact = args
        x_dict, index_dict, e_dict, mask_dict, prev_disp, exact = self._step_inputs(*inputs, states, contact)
        du = self.surrogate.residual_from_features(
            x_dict,
            index_dict,
            e_dict,
            prev_disp,
            mask_dict,
            network=self.surrogate.model,
            draw=iter(noise).__next__,
        )
        pos, tool_next = inputs[0], inputs[2]
        return next_positions(self.ply, pos, du, tool_next), exact

    def _checked(self, call, *args) -> tuple:
        """``call(*args, states, contact)``, searching the contact candidates again where not exact.

        Levels searched at every step (and the edges of the initial state) are passed as
        compacted edge lists; the others as candidate states. ``call`` returns a tuple whose
        last entry holds the per-level exactness flags (dropped here).
        """
        pos = args[0]
        if self._static_contact is not None:
            return call(*args, [None] * self.num_levels, self._static_contact)[:-1]

        def level_pos(k: int) -> Tensor:  # [B N_k, 3], only where a search needs it
            return pos if k == 0 else pos[self.fine_index[k]]

        contact: list[tuple[SlottedEdgeIndex, Tensor] | None] = [None] * self.num_levels
        for k, cand in enumerate(self.candidates):
            if cand.state is None or cand.mode == "search":
                cand.build(level_pos(k))
            if cand.mode == "search":
                contact[k] = self._compact(k, cand.state.nbr, cand.state.mask)
        states = [None if contact[k] is not None else c.state for k, c in enumerate(self.candidates)]
        out = call(*args, states, contact)
        exact = out[-1].tolist()  # per level
        if all(exact):
            return out[:-1]
        for k, cand in enumerate(self.candidates):  # search again where the check failed
            if not exact[k]:
                cand.build(level_pos(k))
        states = [None if contact[k] is not None else c.state for k, c in enumerate(self.candidates)]
        return call(*args, states, contact)[:-1]

    def _compact(self, level: int, nbr: Tensor, mask: Tensor) -> tuple[SlottedEdgeIndex, Tensor]:
        """The used slots of a contact table: edges padded to a capacity, with their slot table; validity.

        The capacity (a multiple of 1024, a quarter above the largest count seen) changes
        rarely, so the compiled step keeps its shapes; padding edges are masked self-loops.
        """
        used = mask.reshape(-1)
        count = int(used.sum())
        if count > self._capacity[level]:
            self._capacity[level] = -(-int(count * 1.25) // 1024) * 1024
        cap = self._capacity[level]
        ids = used.nonzero().squeeze(1)  # row-major: by target, then slot
        pad = cap - count
        rows = self.contact_target[level]
        source = torch.cat([nbr.reshape(-1)[ids], rows.new_zeros(pad)])
        target = torch.cat([rows[ids], rows.new_zeros(pad)])
        valid = torch.arange(cap, device=used.device) < count
        position = torch.cumsum(used.long(), 0) - 1  # index of each used slot in the edge list
        slots = torch.where(mask, position.view(mask.shape), -1)
        return SlottedEdgeIndex(torch.stack([source, target]), slots), valid

    # ---- the rollout ------------------------------------------------------------------------
    @torch.no_grad()
    def __call__(
        self,
        trajectories: Sequence[Trajectory],
        generators: Sequence[torch.Generator | None] | None = None,
        num_steps: int | None = None,
        progress: bool = False,
    ) -> Tensor:
        """Roll out ``B`` trajectories of this mesh from their initial states.

        Args:
            trajectories: ``B`` trajectories (at most ``batch_size``; fewer are padded with the last).
                Their initial states, gripper settings and tool motion are used.
            generators: One noise generator per trajectory (``None``: the default generator).
            num_steps: Steps to roll out (default: all ``T``; every trajectory must have them).
            progress: Show a progress bar.

        Returns:
            Predicted positions ``[B, num_steps + 1, N, 3]`` (float32, CPU); row 0 is the initial state.
        """
        trajs = list(trajectories)
        count = len(trajs)
        if not 1 <= count <= self.batch_size:
            raise ValueError(f"expected 1 to {self.batch_size} trajectories, got {count}")
        for i, traj in enumerate(trajs):
            if traj.num_nodes != self.num_nodes:
                raise ValueError(
                    f"trajectory {i} has {traj.num_nodes} nodes; this FastRollout's mesh has {self.num_nodes}"
                )
        gens = list(generators) if generators is not None else [None] * count
        if len(gens) != count:
            raise ValueError(f"got {len(gens)} generators for {count} trajectories")
        steps = min(t.num_steps for t in trajs) if num_steps is None else num_steps
        if not 1 <= steps <= min(t.num_steps for t in trajs):
            raise ValueError(f"num_steps must be in 1..{min(t.num_steps for t in trajs)}, got {steps}")
        pad = self.batch_size - count
        trajs, gens = trajs + trajs[-1:] * pad, gens + [None] * pad
        dev, n = self.device, self.num_nodes
        tool_path = torch.cat([t.pos[: steps + 1].to(dev).float() for t in trajs], dim=1)  # [T+1, B N, 3]
        # grippers hold ply nodes: their points and forces follow the predicted positions
        gripper_nodes = torch.stack(
            [t.gripper_nodes.to(dev) + i * n for i, t in enumerate(trajs)]
        )  # [B, G, m]
        anchor = torch.stack([t.gripper_anchor.to(dev) for t in trajs]).float()  # [B, G, 3]
        magnitude = torch.stack([t.gripper_force.to(dev) for t in trajs]).float()  # [B, G]
        fiber = torch.cat([t.fiber.to(dev).float() for t in trajs])  # [B N, 3]
        pos0 = tool_path[0]  # [B N, 3]
        pos0_l = [pos0[idx] for idx in self.fine_index]
        prior_path = None
        if self.surrogate.prior_features:
            missing = [i for i, t in enumerate(trajs[:count]) if t.prior is None]
            if missing:
                raise ValueError(
                    f"the surrogate reads a prior (prior_features) but trajectories {missing} have none: "
                    "set their .prior (e.g. a fitted baseline's predict(traj))"
                )
            prior_path = torch.cat(
                [t.prior[: steps + 1].to(dev).float() for t in trajs], dim=1
            )  # [T+1, B N, 3]
        if self.initial_contact:  # ROBIN's edges: from the initial state, once per rollout
            self._static_contact = []
            for k, cand in enumerate(self.candidates):
                nbr, mask = component_radius_table(
                    pos0_l[k],
                    self.level_component[k],
                    self.radius[k],
                    self.k,
                    num_components=self.surrogate.num_components,
                    batch=cand.batch,
                    backend=self.surrogate.contact.backend,
                )
                self._static_contact.append(self._compact(k, nbr, mask))
        ply = self.ply
        pred = tool_path.clone()  # [T+1, B N, 3]: tools on their path, plies predicted
        pred[1:, ply] = pred[0, ply]
        for cand in self.candidates:
            cand.state = None  # a new rollout searches from its initial state
        noise_gens = gens[:count]

        def draw() -> Tensor:  # one [N, 3] sample per real setting, in the plain rollout's order
            parts = [torch.randn(n, 3, generator=g, device=dev) for g in noise_gens]
            parts += [torch.zeros(n, 3, device=dev)] * pad
            return torch.cat(parts)

        iterator = range(1, steps + 1)
        if progress:
            from tqdm.auto import tqdm

            iterator = tqdm(iterator, desc="rollout", unit="step", leave=False)
        # no page faults per step; spinning threads, as many as other processes leave cores
        with retained_heap(self.retain_heap and dev.type == "cpu"), follow_free_cpu(dev) as threads:
            for t in iterator:
                threads.step()
                pos = pred[t - 1]
                prev = pred[max(t - 2, 0)]  # the first step has no previous displacement
                priors = (None, None) if prior_path is None else (prior_path[t - 1], prior_path[t])
                inputs = (pos, prev, tool_path[t], gripper_nodes, anchor, magnitude, fiber, pos0, *priors)
                noise = [draw() for _ in range(self.surrogate.diffusion_steps)]  # drawn once, even on a retry
                # the first step compiles: its kernels are built for every thread torch may use
                with threads.at_ceiling() if self._compile and not self._stepped else nullcontext():
                    if self.surrogate.diffusion_steps == 1:
                        (pred[t],) = self._checked(self._fused, *inputs, noise)
                    else:
                        du = self._residual(*self._checked(self._inputs, *inputs), noise)
                        pred[t] = next_positions(ply, pos, du, pred[t])
                self._stepped = True
        return pred[: steps + 1].view(steps + 1, self.batch_size, n, 3).transpose(0, 1)[:count].cpu()

    def _residual(self, x_dict, index_dict, e_dict, mask_dict, prev_disp, noise: list[Tensor]) -> Tensor:
        """The K-step sampled residual ``[B N, 3]`` from a step's features, with the network ``K`` times."""
        return self.surrogate.residual_from_features(
            x_dict, index_dict, e_dict, prev_disp, mask_dict, network=self._network, draw=iter(noise).__next__
        ).float()
