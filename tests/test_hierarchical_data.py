import pytest
import torch
from torch_geometric.data import Batch
from torch_geometric.loader import DataLoader

from torch_ampn.data import HierarchicalData, build_hierarchy, stacked_plates

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _hierarchy(nx=20, ny=16, layers=2, seed=0):
    m = stacked_plates(nx, ny, layers)
    h = build_hierarchy(m.edge_index(), m.num_nodes, max_levels=3, min_coarse_nodes=4)
    g = torch.Generator().manual_seed(seed)
    h["l0"].pos = m.pos + 0.01 * torch.randn(m.pos.shape, generator=g)
    h["l0"].component = m.component
    h.gripper_force = torch.rand(1, 2, 3, generator=g)  # graph-level: [1, G, 3]
    return h


def test_accessors_and_level_names():
    h = _hierarchy()
    assert h.num_levels == 3
    assert h.node_types == ["l0", "l1", "l2"]
    assert h.level(0) is h["l0"] and h.level(-1) is h["l2"]
    assert h.mesh(1) is h["l1", "mesh", "l1"]
    assert h.contact(2) is h["l2", "contact", "l2"]
    assert h.down(0) is h["l0", "down", "l1"]
    assert h.up(1) is h["l2", "up", "l1"]
    assert h.contact(0).edge_index.shape == (2, 0)
    with pytest.raises(IndexError, match="out of range"):
        h.level(3)
    with pytest.raises(IndexError, match="out of range"):
        h.down(2)  # no level below the coarsest


def test_fine_index_composes_roots():
    h = _hierarchy()
    assert torch.equal(h.fine_index(0), torch.arange(h["l0"].num_nodes))
    assert torch.equal(h.fine_index(1), h["l1"].root)
    expected = torch.tensor([int(h["l1"].root[int(r)]) for r in h["l2"].root])
    assert torch.equal(h.fine_index(2), expected)
    # A root is its own fine node: its position is the coarse node's position.
    pos2 = h["l0"].pos[h.fine_index(2)]
    assert pos2.shape == (h["l2"].num_nodes, 3)


def test_summary_lists_every_level():
    h = _hierarchy()
    text = h.summary()
    lines = text.splitlines()
    assert lines[0] == "HierarchicalData with 3 levels"
    assert len(lines) == 2 + 3
    for k, line in enumerate(lines[2:]):
        cols = line.split()
        assert cols[0] == f"l{k}" and int(cols[1]) == h.level(k).num_nodes
        assert int(cols[2]) == h.mesh(k).edge_index.size(1)
    assert "HierarchicalData(" in repr(h)


def test_batch_offsets_every_level_and_keeps_graph_attributes():
    h1, h2 = _hierarchy(seed=1), _hierarchy(14, 12, 3, seed=2)
    b = Batch.from_data_list([h1, h2])
    assert isinstance(b, HierarchicalData) and b.num_graphs == 2
    for k in range(3):
        n1 = h1.level(k).num_nodes
        assert b.level(k).num_nodes == n1 + h2.level(k).num_nodes
        assert torch.equal(
            b[f"l{k}"].batch, torch.cat([torch.zeros(n1), torch.ones(h2.level(k).num_nodes)]).long()
        )
        assert torch.equal(
            b.mesh(k).edge_index, torch.cat([h1.mesh(k).edge_index, h2.mesh(k).edge_index + n1], 1)
        )
        if k > 0:
            # root indexes level k-1, so it is offset by level k-1's node count.
            m1 = h1.level(k - 1).num_nodes
            assert torch.equal(b.level(k).root, torch.cat([h1.level(k).root, h2.level(k).root + m1]))
        if k < 2:
            offset = torch.tensor([[h1.level(k).num_nodes], [h1.level(k + 1).num_nodes]])
            assert torch.equal(
                b.down(k).edge_index, torch.cat([h1.down(k).edge_index, h2.down(k).edge_index + offset], 1)
            )
            assert torch.equal(
                b.up(k).edge_index, torch.cat([h1.up(k).edge_index, h2.up(k).edge_index + offset.flip(0)], 1)
            )
    assert b.gripper_force.shape == (2, 2, 3)
    # fine_index of the batch equals the per-graph fine indices, offset.
    assert torch.equal(b.fine_index(2), torch.cat([h1.fine_index(2), h2.fine_index(2) + h1["l0"].num_nodes]))
    # And unbatching gives the originals back.
    back = b.get_example(1)
    assert torch.equal(back.level(2).root, h2.level(2).root)
    assert torch.equal(back.down(1).edge_index, h2.down(1).edge_index)


def test_dataloader_batches_hierarchies():
    data = [_hierarchy(seed=s) for s in range(4)]
    loader = DataLoader(data, batch_size=2, shuffle=False)
    batches = list(loader)
    assert len(batches) == 2
    assert batches[1].num_graphs == 2
    assert torch.equal(
        batches[1]["l1"].ptr, torch.tensor([0, data[2]["l1"].num_nodes, 2 * data[2]["l1"].num_nodes])
    )


@pytest.mark.parametrize("device", DEVICES)
def test_to_device_moves_everything(device):
    h = _hierarchy().to(device)
    assert h.fine_index(2).device.type == device
    for store in h.stores:
        for value in store.values():
            if isinstance(value, torch.Tensor):
                assert value.device.type == device


@pytest.mark.skipif(not torch.cuda.is_available(), reason="pinning memory needs CUDA")
@pytest.mark.gpu
def test_pin_memory():
    h = _hierarchy().pin_memory()
    assert h.mesh(0).edge_index.is_pinned()


@pytest.mark.parametrize("how", ["save_load", "torch"])
def test_save_and_load_round_trip(tmp_path, how):
    h = _hierarchy()
    if how == "save_load":
        h.save(tmp_path / "h.pt")
        assert [p.name for p in tmp_path.iterdir()] == ["h.pt"]  # no temporary file left
        back = HierarchicalData.load(tmp_path / "h.pt")  # weights_only unpickling
    else:
        torch.save(h, tmp_path / "h.pt")
        back = torch.load(tmp_path / "h.pt", weights_only=False)
    assert isinstance(back, HierarchicalData)
    assert back.gripper_force.shape == (1, 2, 3)
    assert back.num_levels == h.num_levels
    for k in range(h.num_levels):
        assert torch.equal(back.mesh(k).edge_index, h.mesh(k).edge_index)
    assert torch.equal(back["l0"].pos, h["l0"].pos)
    assert torch.equal(back.down(0).edge_weight, h.down(0).edge_weight)


def test_fixed_size_contact_table_is_offset_when_batched():
    h1, h2 = _hierarchy(seed=1), _hierarchy(14, 12, 3, seed=2)
    for h in (h1, h2):
        for k in range(h.num_levels):
            n = h.level(k).num_nodes
            h[f"l{k}"].contact_nbr = torch.arange(n).repeat_interleave(3).view(n, 3).flip(0)
    b = Batch.from_data_list([h1, h2])
    for k in range(3):
        n1 = h1.level(k).num_nodes
        assert torch.equal(
            b[f"l{k}"].contact_nbr, torch.cat([h1[f"l{k}"].contact_nbr, h2[f"l{k}"].contact_nbr + n1])
        )
