"""benchmarks/peers.py: PhysicsNeMo's MeshGraphNets behind AMPN's interface, and their compare.py cells.

These need the peers' environment (``source scripts/install_peers.sh``: NVIDIA PhysicsNeMo 2.2.2 and
torch-scatter); they are skipped elsewhere, with that reason.
"""

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmarks.peers

from benchmarks.peers import physicsnemo_available  # noqa: E402

REASON = physicsnemo_available()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"the PhysicsNeMo peers: {REASON}")

MESH, CONTACT = ("l0", "mesh", "l0"), ("l0", "contact", "l0")


def _inputs(num_nodes=12, num_mesh=30, num_contact=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    x_dict = {
        "l0": torch.randn(num_nodes, 5, generator=g),
        "pos": torch.randn(num_nodes, 3, generator=g),
        "pos0": torch.randn(num_nodes, 3, generator=g),
    }
    mesh = torch.randint(0, num_nodes, (2, num_mesh), generator=g)
    mesh = torch.cat([mesh, mesh.flip(0)], dim=1)  # both directions, as our mesh edges
    index = {MESH: mesh, CONTACT: torch.randint(0, num_nodes, (2, num_contact), generator=g)}
    attr = {
        MESH: torch.randn(mesh.size(1), 8, generator=g),
        CONTACT: torch.randn(num_contact, 4, generator=g),
    }
    noise = torch.randn(num_nodes, 3, generator=g)
    return x_dict, index, attr, noise


def _adapter(name):
    import benchmarks.peers as peers

    torch.manual_seed(0)
    cls = getattr(peers, name)
    return cls(5, hidden_channels=16, processor_size=2).eval()


@pytest.mark.parametrize("name", ["PhysicsNeMoHybrid", "PhysicsNeMoBSMS"])
def test_the_adapter_is_the_peers_own_class_fed_our_edges(name):
    from torch_geometric.data import Data

    from benchmarks.peers import import_physicsnemo

    peer = import_physicsnemo()  # physicsnemo.models.meshgraphnet
    adapter = _adapter(name)
    x_dict, index, attr, noise = _inputs()
    out = adapter(x_dict, index, attr, noise=noise)
    x = torch.cat([x_dict["l0"], noise], dim=1)
    world = torch.nn.functional.pad(attr[CONTACT], (0, 4))  # 4 contact columns padded to the mesh's 8
    edges = torch.cat([index[MESH], index[CONTACT]], dim=1)
    if name == "PhysicsNeMoHybrid":
        assert type(adapter.net) is peer.HybridMeshGraphNet
        expected = adapter.net(x, attr[MESH], world, Data(edge_index=edges, num_nodes=12))
    else:
        assert type(adapter.net) is peer.BiStrideMeshGraphNet
        kind = torch.cat([torch.zeros(index[MESH].size(1), 1), torch.ones(8, 1)])
        feats = torch.cat([torch.cat([attr[MESH], world]), kind], dim=1)
        ms_edges, ms_ids = adapter.bistride_hierarchy(index[MESH], x_dict["pos0"])
        assert len(ms_ids) == 2 and all(len(i) < 12 for i in ms_ids)  # two pooled levels
        graph = Data(edge_index=edges, pos=x_dict["pos"], num_nodes=12)
        expected = adapter.net(x, feats, graph, ms_edges=ms_edges, ms_ids=ms_ids)
    assert out.shape == (12, 3)
    torch.testing.assert_close(out, expected, rtol=0, atol=0)


def test_nodes_relabelled_give_the_same_outputs_relabelled():
    """The hybrid model only (the bi-stride pooling's seeds depend on the node order)."""
    adapter = _adapter("PhysicsNeMoHybrid")
    x_dict, index, attr, noise = _inputs()
    perm = torch.randperm(12, generator=torch.Generator().manual_seed(3))
    inverse = torch.argsort(perm)  # new label of old node i: inverse[i]
    x_p = {k: v[perm] for k, v in x_dict.items()}
    index_p = {k: inverse[v] for k, v in index.items()}
    out = adapter(x_dict, index, attr, noise=noise)
    out_p = adapter(x_p, index_p, attr, noise=noise[perm])
    torch.testing.assert_close(out_p, out[perm], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["PhysicsNeMoHybrid", "PhysicsNeMoBSMS"])
def test_a_step_without_contact_edges_runs(name):
    """PhysicsNeMo #1123 (HybridMeshGraphNet and a step with no world edge): no contact key, an empty
    contact set and a table whose slots are all masked give the same, finite output."""
    adapter = _adapter(name)
    x_dict, index, attr, noise = _inputs()
    without = adapter(x_dict, {MESH: index[MESH]}, {MESH: attr[MESH]}, noise=noise)
    empty = {MESH: index[MESH], CONTACT: index[CONTACT][:, :0]}
    empty_attr = {MESH: attr[MESH], CONTACT: attr[CONTACT][:0]}
    masked = {CONTACT: torch.zeros(8, dtype=torch.bool)}
    assert torch.isfinite(without).all()
    torch.testing.assert_close(adapter(x_dict, empty, empty_attr, noise=noise), without, rtol=0, atol=0)
    torch.testing.assert_close(adapter(x_dict, index, attr, noise=noise, contact_mask_dict=masked), without)
    half = torch.arange(8) % 2 == 0
    kept = {MESH: index[MESH], CONTACT: index[CONTACT][:, half]}
    kept_attr = {MESH: attr[MESH], CONTACT: attr[CONTACT][half]}
    torch.testing.assert_close(
        adapter(x_dict, index, attr, noise=noise, contact_mask_dict={CONTACT: half}),
        adapter(x_dict, kept, kept_attr, noise=noise),
    )


def test_the_adapters_refuse_what_they_cannot_run():
    import benchmarks.peers as peers

    with pytest.raises(ValueError, match="num_levels: 1"):
        peers.PhysicsNeMoHybrid(5, num_levels=3)
    with pytest.raises(ValueError, match="diffusion_steps = 1 only"):
        peers.PhysicsNeMoBSMS(5, num_step_frequencies=4)


def _load_compare():
    spec = importlib.util.spec_from_file_location("compare", ROOT / "benchmarks" / "compare.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["compare"] = module
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_peer_cells_end_to_end(tmp_path, tiny_data):
    import yaml
    from helpers import tiny_cli_config

    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(tiny_cli_config(data={"generate": False})))
    compare = _load_compare()
    args = [
        "--config", str(tmp_path / "tiny.yaml"), "--data-dir", str(tiny_data), "--steps", "3",
        "--seeds", "0", "--results", str(tmp_path / "results"), "--workdir", str(tmp_path / "work"),
        "--simulator-mode", "eager", "--no-figures",
    ]  # fmt: skip
    peers = ["physicsnemo_hybrid", "physicsnemo_bsms"]
    assert compare.main([*args, "--variants", *peers]) == 0
    for variant in peers:
        cell = json.loads((tmp_path / "results" / f"{variant}_seed0.json").read_text())
        summary = json.loads(
            (tmp_path / "work" / f"{variant}_seed0" / "test" / "test_summary.json").read_text()
        )
        assert cell["rmse"] == pytest.approx(summary["rollout_rmse"]) and cell["num_levels"] == 1
        assert cell["layer_applications"] == cell["layers"] and cell["parameters"] > 0
    table = json.loads((tmp_path / "results" / "table.json").read_text())
    rows = {r["variant"]: r for r in table["rows"]}
    assert all(rows[v]["seeds"] == [0] for v in peers)  # the report finds the peers' cells by itself
