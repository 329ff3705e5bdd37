import pytest
import torch
from torch_geometric.loader import DataLoader

from torch_ampn.data import HierarchicalData, StepDataset, TrajectoryDataset, step_sample
from torch_ampn.data import dataset as dataset_module
from torch_ampn.hierarchy import amg as hierarchy_module
from torch_ampn.testing import small_trajectory


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    for split, seeds in (("train", [0, 1, 2]), ("val", [3])):
        for s in seeds:
            small_trajectory(steps=4, seed=s).save(root / split / f"traj_{s:06d}.pt")
    return root


def test_trajectory_dataset_lists_and_loads(root):
    ds = TrajectoryDataset(root, "train")
    assert len(ds) == 3 and [t.meta["seed"] for t in ds] == [0, 1, 2]
    assert "trajectories=3" in repr(ds)
    with pytest.raises(FileNotFoundError, match="test: no trajectory files"):
        TrajectoryDataset(root, "test")
    with pytest.raises(ValueError, match="split must be one of"):
        TrajectoryDataset(root, "training")


def test_step_sample_fields_by_hand(root):
    traj = TrajectoryDataset(root, "train")[1]
    ds = StepDataset(root, "train", cache_dir=None, min_coarse_nodes=2)
    assert len(ds) == 3 * 4
    assert ds.index(5) == (1, 2)
    data = ds[5]
    assert isinstance(data, HierarchicalData)
    l0 = data["l0"]
    assert torch.equal(l0.pos, traj.pos[1]) and torch.equal(l0.pos0, traj.pos[0])
    assert torch.equal(l0.target, traj.pos[2] - traj.pos[1])
    assert torch.equal(l0.prev_disp, traj.pos[1] - traj.pos[0])
    tool = ~traj.ply_mask
    assert torch.equal(l0.bc_disp[tool], (traj.pos[2] - traj.pos[1])[tool])
    assert torch.equal(l0.bc_disp[traj.ply_mask], torch.zeros_like(l0.bc_disp[traj.ply_mask]))
    assert torch.allclose(data.gripper_pos[0], traj.gripper_positions()[1])
    assert data.gripper_force.shape == (1, 1, 3) and int(data.step) == 2 and int(data.traj_index) == 1
    # the window before (t-2, t-1) = (0, 1): no residual before it, grippers at step 0
    assert torch.equal(l0.prev_prev_disp, torch.zeros_like(l0.prev_prev_disp))
    assert torch.allclose(data.prev_gripper_pos[0], traj.gripper_positions()[0])
    assert torch.allclose(data.prev_gripper_force[0], traj.gripper_force_vectors()[0])
    later = ds[7]  # t = 4
    assert torch.equal(later["l0"].prev_prev_disp, traj.pos[2] - traj.pos[1])
    assert torch.allclose(later.prev_gripper_pos[0], traj.gripper_positions()[2])
    # coarse levels carry their roots' node type and component
    for k in range(1, data.num_levels):
        assert torch.equal(data[f"l{k}"].node_type, traj.node_type[data.fine_index(k)])
    first = step_sample(traj, 1, ds.hierarchies(traj))
    assert torch.equal(first["l0"].prev_disp, torch.zeros_like(first["l0"].prev_disp))
    with pytest.raises(IndexError):
        step_sample(traj, 0, ds.hierarchies(traj))


def test_hierarchy_built_once_per_topology(root, monkeypatch):
    calls = []
    real = hierarchy_module.build_hierarchy

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(dataset_module, "build_hierarchy", counting)
    ds = StepDataset(root, "train", cache_dir=None, min_coarse_nodes=2)
    samples = [ds[i] for i in range(len(ds))]
    assert len(calls) == 1  # three trajectories, one mesh
    # samples do not share their per-step fields through the cached hierarchy
    assert not torch.equal(samples[0]["l0"].pos, samples[5]["l0"].pos)
    assert "pos" not in ds.hierarchies(ds.trajectories[0])["l0"]


def test_samples_batch_with_pyg_dataloader(root):
    ds = StepDataset(root, "train", cache_dir=root / "cache", min_coarse_nodes=2)
    batch = next(iter(DataLoader(ds, batch_size=3, shuffle=False)))
    n = ds[0]["l0"].num_nodes
    assert batch.num_graphs == 3 and batch["l0"].pos.shape == (3 * n, 3)
    assert batch.gripper_pos.shape == (3, 1, 3)
    assert torch.equal(batch.step, torch.tensor([1, 2, 3]))
    assert list((root / "cache").glob("hierarchy-*.pt"))


def test_cached_samples_are_built_once_and_equal_fresh_ones(root):
    from torch_ampn.transforms import ComponentRadiusGraph

    calls = []
    contact = ComponentRadiusGraph(r=5.0, k=2)

    def counting(data):
        calls.append(1)
        return contact(data)

    cached = StepDataset(
        root, "train", cache_dir=None, min_coarse_nodes=2, transform=counting, cache_samples=True
    )
    fresh = StepDataset(root, "train", cache_dir=None, min_coarse_nodes=2, transform=contact)
    for _ in range(2):  # two epochs
        batches = list(DataLoader(cached, batch_size=1, shuffle=True))
    assert len(calls) == len(cached)  # the second epoch built nothing
    for i in range(len(cached)):
        a, b = cached[i], fresh[i]
        for key in b.edge_types:
            assert torch.equal(a[key].edge_index, b[key].edge_index)
        assert torch.equal(a["l0"].pos, b["l0"].pos) and torch.equal(a["l0"].target, b["l0"].target)
    # training noise replaces a batch's tensors; the cached windows keep theirs
    batch = batches[0]
    i = int(batch.traj_index) * 4 + int(batch.step) - 1
    batch["l0"].pos = batch["l0"].pos + 1.0
    assert torch.equal(cached[i]["l0"].pos, fresh[i]["l0"].pos)


def test_trajectory_memory_is_capped_least_recently_used_first(root, monkeypatch):
    from torch_ampn.data import Trajectory
    from torch_ampn.data.dataset import _tensor_bytes

    loads = []
    real = Trajectory.load
    monkeypatch.setattr(Trajectory, "load", staticmethod(lambda path: loads.append(path.name) or real(path)))
    one = _tensor_bytes(real(TrajectoryDataset(root, "train").files[0]))
    capped = TrajectoryDataset(root, "train", max_cached_mb=2.5 * one / 1e6)  # room for two
    for i in (0, 1, 0, 2, 1, 0):
        assert torch.equal(capped[i].pos, real(capped.files[i]).pos)
    names = [f.name for f in capped.files]  # (the reference loads above call the real load directly)
    # 0, 1 loaded; 0 cached; 2 loaded (drops 1, the least recently used); 1 loaded (drops 0); 0 loaded
    assert loads == [names[i] for i in (0, 1, 2, 1, 0)]
    assert list(capped._cache) == [1, 0] and capped._cached_bytes == 2 * one
    unlimited = TrajectoryDataset(root, "train", max_cached_mb=None)
    for i in (0, 1, 2, 0):
        unlimited[i]
    assert len(unlimited._cache) == 3
