"""The peers' own networks behind AMPN's interface: NVIDIA PhysicsNeMo's MeshGraphNets.

``benchmarks/compare.py``'s ``physicsnemo_*`` variants train and test these in place of the AMPN
(``model.network_class``, see :class:`~torch_ampn.forming.AMPNSurrogate`), on the same data, features,
normalisation, noise, pushforward, step budget and (plain-path) rollout. The peer's model class is
imported from the peer's package and used unmodified; an adapter only translates AMPN's inputs
(``x_dict``, ``edge_index_dict``, ``edge_attr_dict`` of :meth:`torch_ampn.nn.AMPN.forward`) into
the peer's and hands the peer's output back:

* :class:`PhysicsNeMoHybrid`: ``HybridMeshGraphNet`` (PhysicsNeMo's deforming-plate model): the
  fine mesh edges as its mesh edges, our contact edges as its world edges.
* :class:`PhysicsNeMoBSMS`: ``BiStrideMeshGraphNet`` (BSMS-GNN): one edge set (mesh and contact
  edges, with a column that tells them apart) and its bi-stride pooling hierarchy of the mesh,
  built by PhysicsNeMo's ``BistrideMultiLayerGraph`` from the initial positions, once per mesh.

Both take the fine level only (``model.num_levels: 1``), the same node features as the AMPN plus
its noise input, and edge features zero-padded to the mesh edges' width (the peer encodes mesh and
world edges with one input width). Install: ``source scripts/install_peers.sh`` (its own virtual
environment; PhysicsNeMo 2.2.2 needs torch-scatter, built from source there).

On CPU-only torch, ``torchvision`` from PyPI is a CUDA build that fails to import, and PhysicsNeMo's
package imports ``timm`` (which imports torchvision) for its transformer layers at import time;
:func:`import_physicsnemo` then puts a placeholder ``timm`` in ``sys.modules`` whose classes raise
when used. The MeshGraphNets use neither.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import sys
import types
from typing import Any

import torch
from torch import Tensor, nn

from torch_ampn.hierarchy.hierarchical_data import edge_type

MESH_EDGE_CHANNELS = 8  # torch_ampn.forming.features.EDGE_FEATURES_WITH_INITIAL
CONTACT_EDGE_CHANNELS = 4  # torch_ampn.forming.features.EDGE_FEATURES_CURRENT
_TIMM_MODULES = (
    "timm",
    "timm.layers",
    "timm.layers.attention",
    "timm.models",
    "timm.models.swin_transformer",
)


def _placeholder_module(name: str) -> types.ModuleType:
    """A module whose every attribute is a class that raises when instantiated."""
    module = types.ModuleType(name)
    module.__spec__ = importlib.machinery.ModuleSpec(name, None)
    module.__path__ = []

    def __getattr__(attr: str) -> type:
        if attr.startswith("__"):
            raise AttributeError(attr)

        def unavailable(*args: Any, **kwargs: Any) -> None:
            raise RuntimeError(f"{name}.{attr} is a placeholder (timm needs a working torchvision)")

        return type(attr, (), {"__init__": unavailable})

    module.__getattr__ = __getattr__  # type: ignore[method-assign]
    return module


def _torchvision_works() -> bool:
    if importlib.util.find_spec("torchvision") is None:
        return False
    try:
        importlib.import_module("torchvision")
    except Exception:  # noqa: BLE001 - a CUDA build on CPU torch raises RuntimeError
        for key in [k for k in sys.modules if k == "torchvision" or k.startswith("torchvision.")]:
            del sys.modules[key]
        return False
    return True


def physicsnemo_available() -> str | None:
    """``None`` where PhysicsNeMo's MeshGraphNets can run here, else why not (one line)."""
    missing = [p for p in ("physicsnemo", "torch_scatter") if importlib.util.find_spec(p) is None]
    if missing:
        return f"{' and '.join(missing)} not installed (source scripts/install_peers.sh)"
    return None


def import_physicsnemo() -> types.ModuleType:
    """``physicsnemo.models.meshgraphnet``, with a placeholder ``timm`` where torchvision is broken."""
    reason = physicsnemo_available()
    if reason is not None:
        raise ImportError(f"the PhysicsNeMo peers: {reason}")
    if "timm" not in sys.modules and not _torchvision_works():
        for name in _TIMM_MODULES:
            sys.modules[name] = _placeholder_module(name)
    return importlib.import_module("physicsnemo.models.meshgraphnet")


def _contact_edges(
    edge_index_dict: dict, edge_attr_dict: dict, contact_mask_dict: dict | None, like: Tensor
) -> tuple[Tensor, Tensor]:
    """The fine contact edges ``([2, E_c], [E_c, F_c])``; none if the step has none; masked slots dropped."""
    key = edge_type("contact", 0)
    if key not in edge_index_dict:
        return like.new_empty(2, 0, dtype=torch.long), like.new_empty(0, CONTACT_EDGE_CHANNELS)
    index, attr = edge_index_dict[key], edge_attr_dict[key]
    mask = None if contact_mask_dict is None else contact_mask_dict.get(key)
    if mask is not None:
        index, attr = index[:, mask], attr[mask]
    return index, attr


def _pad(attr: Tensor, width: int) -> Tensor:
    """``attr`` ``[E, F]`` with zero columns up to ``width``."""
    return torch.nn.functional.pad(attr, (0, width - attr.size(1)))


def _mgn_sizes(processor_size: int, hidden: int, mlp_layers: int, aggregation: str) -> dict[str, Any]:
    """The size arguments every PhysicsNeMo MeshGraphNet takes: one width and one MLP depth throughout."""
    sizes: dict[str, Any] = {"processor_size": processor_size, "aggregation": aggregation}
    for part in ("processor", "node_encoder", "edge_encoder", "node_decoder"):
        sizes[f"hidden_dim_{part}"] = hidden
    for part in ("node_processor", "edge_processor", "node_encoder", "edge_encoder", "node_decoder"):
        sizes[f"num_layers_{part}"] = mlp_layers
    return sizes


class _PeerAdapter(nn.Module):
    """What :class:`~torch_ampn.nn.DiffusionAMPN` and the surrogate read of a network."""

    step_encoding = None  # no diffusion-step conditioning: K = 1 only

    def __init__(self, num_levels: int, noise_channels: int, num_step_frequencies: int, out_channels: int):
        super().__init__()
        if num_step_frequencies:
            raise ValueError(f"{type(self).__name__}: the peers run with diffusion_steps = 1 only")
        if num_levels != 1:
            raise ValueError(
                f"{type(self).__name__}: set model.num_levels: 1 (the peer takes the fine level only)"
            )
        self.noise_channels = noise_channels
        self.out_channels = out_channels

    @property
    def layer_applications(self) -> int:
        """Message-passing layers applied per call: each of the peer's ``num_layers`` once."""
        return self.num_layers

    def _inputs(
        self,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict,
        edge_attr_dict: dict,
        noise: Tensor | None,
        contact_mask_dict: dict | None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(x [N_0, F + 3], mesh index [2, E_m], mesh features [E_m, 8], contact index, features)``."""
        x = self._node_input(x_dict, noise)
        mesh = edge_type("mesh", 0)
        contact = _contact_edges(edge_index_dict, edge_attr_dict, contact_mask_dict, x)
        return x, edge_index_dict[mesh], edge_attr_dict[mesh], *contact

    def _node_input(self, x_dict: dict[str, Tensor], noise: Tensor | None) -> Tensor:
        x = x_dict["l0"]  # [N_0, F]
        if self.noise_channels:
            if noise is None:
                raise ValueError(f"{type(self).__name__} has a noise input: pass `noise`")
            x = torch.cat([x, noise.to(x.dtype)], dim=-1)  # [N_0, F + 3], as the AMPN's input
        return x


class PhysicsNeMoHybrid(_PeerAdapter):
    r"""PhysicsNeMo's ``HybridMeshGraphNet`` on the fine level: mesh edges and contact (world) edges.

    Args:
        fine_in_channels: Node features of ``l0`` (without the noise input).
        num_levels: Must be 1.
        noise_channels: Noise input columns appended to the node features (3, as the AMPN's).
        num_step_frequencies: Must be 0 (no diffusion steps).
        max_step: Unused.
        out_channels: Outputs per node (3).
        hidden_channels: Width of every encoder, processor and decoder MLP (PhysicsNeMo: 128).
        processor_size: Message-passing blocks (PhysicsNeMo: 15).
        mlp_layers: Layers of every MLP (PhysicsNeMo: 2).
        aggregation: ``"sum"`` (PhysicsNeMo's default) or ``"mean"``.
    """

    def __init__(
        self,
        fine_in_channels: int,
        num_levels: int = 1,
        noise_channels: int = 3,
        num_step_frequencies: int = 0,
        max_step: int = 1,
        out_channels: int = 3,
        hidden_channels: int = 128,
        processor_size: int = 15,
        mlp_layers: int = 2,
        aggregation: str = "sum",
    ) -> None:
        super().__init__(num_levels, noise_channels, num_step_frequencies, out_channels)
        peer = import_physicsnemo()
        self.num_layers = processor_size
        self.net = peer.HybridMeshGraphNet(
            fine_in_channels + noise_channels, MESH_EDGE_CHANNELS, out_channels,
            **_mgn_sizes(processor_size, hidden_channels, mlp_layers, aggregation),
        )  # fmt: skip

    def forward(
        self,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict,
        edge_attr_dict: dict,
        noise: Tensor | None = None,
        step: Tensor | None = None,
        batch_dict: dict | None = None,
        contact_mask_dict: dict | None = None,
    ) -> Tensor:
        """The peer's output ``[N_0, out_channels]`` (arguments as :meth:`torch_ampn.nn.AMPN.forward`)."""
        from torch_geometric.data import Data

        x, mesh_index, mesh_attr, world_index, world_attr = self._inputs(
            x_dict, edge_index_dict, edge_attr_dict, noise, contact_mask_dict
        )
        graph = Data(edge_index=torch.cat([mesh_index, world_index], dim=1), num_nodes=x.size(0))
        return self.net(x, mesh_attr, _pad(world_attr, MESH_EDGE_CHANNELS), graph)


class PhysicsNeMoBSMS(_PeerAdapter):
    r"""PhysicsNeMo's ``BiStrideMeshGraphNet`` (BSMS-GNN) on the fine level.

    Its one edge set holds the mesh edges and the contact edges (features zero-padded to the mesh
    edges' 8 columns, and a ninth column: 0 mesh, 1 contact); its bi-stride pooling hierarchy
    (``num_mesh_levels`` pooled levels) comes from the mesh edges and the initial positions,
    built once per mesh by PhysicsNeMo's ``BistrideMultiLayerGraph`` and cached here. The
    bi-stride layers see the current (normalised) positions, as BSMS-GNN's do.

    Args:
        fine_in_channels: Node features of ``l0`` (without the noise input).
        num_levels: Must be 1 (our hierarchy is not used).
        noise_channels: Noise input columns appended to the node features (3, as the AMPN's).
        num_step_frequencies: Must be 0 (no diffusion steps).
        max_step: Unused.
        out_channels: Outputs per node (3).
        hidden_channels: Width of every MLP (PhysicsNeMo: 128).
        processor_size: Message-passing blocks before the bi-stride U-Net (PhysicsNeMo: 15).
        mlp_layers: Layers of every MLP (PhysicsNeMo: 2).
        num_mesh_levels: Pooled levels of the bi-stride hierarchy (PhysicsNeMo: 2).
        bistride_unet_levels: Passes of the bi-stride U-Net (PhysicsNeMo: 1).
        aggregation: ``"sum"`` (PhysicsNeMo's default) or ``"mean"``.
    """

    needs_positions = True

    def __init__(
        self,
        fine_in_channels: int,
        num_levels: int = 1,
        noise_channels: int = 3,
        num_step_frequencies: int = 0,
        max_step: int = 1,
        out_channels: int = 3,
        hidden_channels: int = 128,
        processor_size: int = 15,
        mlp_layers: int = 2,
        num_mesh_levels: int = 2,
        bistride_unet_levels: int = 1,
        aggregation: str = "sum",
    ) -> None:
        super().__init__(num_levels, noise_channels, num_step_frequencies, out_channels)
        peer = import_physicsnemo()
        self.num_mesh_levels = num_mesh_levels
        # message-passing blocks, then per U-Net pass: num_mesh_levels down + bottom + num_mesh_levels up
        self.num_layers = processor_size + bistride_unet_levels * (2 * num_mesh_levels + 1)
        self.net = peer.BiStrideMeshGraphNet(
            fine_in_channels + noise_channels, MESH_EDGE_CHANNELS + 1, out_channels,
            num_mesh_levels=num_mesh_levels, bistride_pos_dim=3, num_layers_bistride=mlp_layers,
            bistride_unet_levels=bistride_unet_levels,
            **_mgn_sizes(processor_size, hidden_channels, mlp_layers, aggregation),
        )  # fmt: skip
        self._hierarchies: dict[str, tuple[list[Tensor], list[Tensor]]] = {}

    def bistride_hierarchy(self, mesh_index: Tensor, pos0: Tensor) -> tuple[list[Tensor], list[Tensor]]:
        """``(ms_edges, ms_ids)`` of the mesh (PhysicsNeMo's ``BistrideMultiLayerGraph``), cached."""
        key = hashlib.sha256(mesh_index.cpu().numpy().tobytes() + pos0.cpu().numpy().tobytes()).hexdigest()
        if key not in self._hierarchies:
            from physicsnemo.datapipes.gnn.bsms import BistrideMultiLayerGraph
            from torch_geometric.data import Data

            graph = Data(edge_index=mesh_index.cpu(), pos=pos0.detach().cpu(), num_nodes=pos0.size(0))
            _, ms_edges, ms_ids = BistrideMultiLayerGraph(
                graph, self.num_mesh_levels
            ).get_multi_layer_graphs()
            device = mesh_index.device
            self._hierarchies[key] = (
                [torch.as_tensor(e, dtype=torch.long, device=device) for e in ms_edges],
                [torch.as_tensor(i, dtype=torch.long, device=device) for i in ms_ids],
            )
        return self._hierarchies[key]

    def forward(
        self,
        x_dict: dict[str, Tensor],
        edge_index_dict: dict,
        edge_attr_dict: dict,
        noise: Tensor | None = None,
        step: Tensor | None = None,
        batch_dict: dict | None = None,
        contact_mask_dict: dict | None = None,
    ) -> Tensor:
        """The peer's output ``[N_0, out_channels]``; ``x_dict`` also holds ``"pos"`` and ``"pos0"``."""
        from torch_geometric.data import Data

        x, mesh_index, mesh_attr, contact_index, contact_attr = self._inputs(
            x_dict, edge_index_dict, edge_attr_dict, noise, contact_mask_dict
        )
        kind = torch.cat(
            [mesh_attr.new_zeros(mesh_attr.size(0), 1), mesh_attr.new_ones(contact_attr.size(0), 1)]
        )
        attr = torch.cat([torch.cat([mesh_attr, _pad(contact_attr, MESH_EDGE_CHANNELS)]), kind], dim=1)
        ms_edges, ms_ids = self.bistride_hierarchy(mesh_index, x_dict["pos0"])
        graph = Data(
            edge_index=torch.cat([mesh_index, contact_index], dim=1), pos=x_dict["pos"], num_nodes=x.size(0)
        )
        return self.net(x, attr, graph, ms_edges=ms_edges, ms_ids=ms_ids)
