"""The fast rollout: contact candidates, slot aggregation, FastRollout against the plain path."""

import dataclasses
import warnings

import pytest
import torch
from helpers import eager_fast_rollout

from torch_ampn.data import HierarchyCache, step_sample
from torch_ampn.forming import AMPNSurrogate
from torch_ampn.nn import InterLevelConv, IntraLevelConv, SlottedEdgeIndex, incoming_slots
from torch_ampn.rollout import rollout
from torch_ampn.rollout.cache import cached_fast_rollout
from torch_ampn.rollout.fast import FastRollout
from torch_ampn.testing import contact_edges_brute_force, random_edge_index, small_trajectory
from torch_ampn.transforms import component_radius_table, table_to_edge_index
from torch_ampn.transforms.candidates import ContactCandidates


# ---- contact candidates ----------------------------------------------------------------------
def _walk(steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Three components of 40 nodes in a box, moving by a random walk (ties included at t = 0)."""
    g = torch.Generator().manual_seed(seed)
    grid = torch.stack(torch.meshgrid(torch.arange(5.0), torch.arange(8.0), indexing="ij"), -1).reshape(-1, 2)
    pos0 = torch.cat([torch.cat([grid, torch.full((40, 1), 0.7 * c)], 1) for c in range(3)])  # [120, 3]
    walk = torch.cumsum(0.03 * torch.randn(steps, 120, 3, generator=g), 0)
    return torch.cat([pos0[None], pos0[None] + walk]), torch.arange(3).repeat_interleave(40)


@pytest.mark.parametrize("mode", ["dense", "patches", "verlet", "search"])
@pytest.mark.parametrize("k", [1, 3])
def test_candidates_give_the_searched_table_at_every_step(mode, k):
    pos, comp = _walk(30, seed=k)
    batch = torch.arange(2).repeat_interleave(60)  # two graphs: never linked across
    cand = ContactCandidates(
        comp, 1.6, k, num_components=3, batch=batch, skin=0.4, capacity=4 * k + 4, mode=mode
    )
    for t in range(pos.size(0)):
        nbr, mask = cand(pos[t])
        ref_nbr, ref_mask = component_radius_table(pos[t], comp, 1.6, k, num_components=3, batch=batch)
        assert torch.equal(nbr, ref_nbr) and torch.equal(mask, ref_mask), t
    if mode == "verlet":  # the small skin forces searches, but not one per step
        assert 1 < cand.searches < pos.size(0)
    if mode in ("dense", "patches"):  # the patches of t = 0 hold: never searched again
        assert cand.searches == 1


def test_candidates_match_brute_force_per_graph():
    pos, comp = _walk(3, seed=5)
    cand = ContactCandidates(comp, 1.2, 2, mode="verlet", skin=0.1, capacity=2)
    for t in range(pos.size(0)):
        edges = table_to_edge_index(*cand(pos[t]))
        ref = contact_edges_brute_force(pos[t], comp, 1.2, 2)
        assert torch.equal(edges, ref)


def test_candidate_check_fails_when_a_far_node_comes_close():
    """Hand case: 1 candidate kept; a node outside the list moves next to the query node."""
    pos = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])  # node 0 (comp 0); 1, 2 (comp 1)
    comp = torch.tensor([0, 1, 1])
    cand = ContactCandidates(comp, 3.0, 1, skin=0.0, capacity=1, mode="verlet")
    cand.build(pos)
    assert cand.select(pos)[2]  # as searched
    moved = pos.clone()
    moved[2, 0] = 0.5  # now nearer than the candidate (node 1)
    assert not cand.select(moved)[2]
    nbr, mask = cand(moved)  # searches again
    assert nbr[0].tolist() == [2] and mask[0].tolist() == [True] and cand.searches == 2


def test_patch_candidates_are_exact_or_say_so():
    """Hand case: cells of edge r = 1, so every node below is a patch of its own.

    Node 0 reaches one patch of component 1 at the first call, so 1 + 2 (the margin) are
    kept. Three nodes of component 1 moving next to it still fit; a fourth does not, and the
    selection must say so (``__call__`` then cuts new patches)."""
    pos = torch.tensor([[0.5, 0.5, 0.0], [0.5, 0.5, 0.3], [1.5, 0.5, 0.3], [5.5, 0.5, 0.3], [8.5, 0.5, 0.3]])
    comp = torch.tensor([0, 1, 1, 1, 1])
    cand = ContactCandidates(comp, 1.0, 1, mode="patches")
    state = cand.build(pos)
    assert state.members.size(0) == 5 and state.capacity == 3
    nbr, mask, exact = cand.select(pos)
    assert exact and nbr[0].tolist() == [1] and mask[0].tolist() == [True]
    assert nbr[1].tolist() == [0] and not mask[2]  # node 2 is 1.04 from node 0: beyond r
    moved = pos.clone()
    moved[2:4, 0] = torch.tensor([0.2, 0.9])  # two more nodes of component 1 next to node 0
    nbr, mask, exact = cand.select(moved)
    ref = component_radius_table(moved, comp, 1.0, 1)
    assert exact and torch.equal(nbr, ref[0]) and torch.equal(mask, ref[1])
    moved[4, 0] = 0.6  # the fourth patch within reach: more than the 3 kept
    assert not cand.select(moved)[2]
    nbr, mask = cand(moved)  # new patches, cut at these positions
    ref = component_radius_table(moved, comp, 1.0, 1)
    assert torch.equal(nbr, ref[0]) and torch.equal(mask, ref[1]) and cand.searches == 2
    assert cand.select(moved)[2]


# ---- slot aggregation ------------------------------------------------------------------------
@pytest.mark.parametrize("aggr", ["max", "sum", "mean"])
def test_slot_aggregation_equals_propagate(aggr):
    torch.manual_seed(0)
    n, d = 9, 8
    conv = IntraLevelConv(d, 16, aggr=aggr)
    x = torch.randn(n, d)
    mesh = random_edge_index(n, n, 30)
    mesh = mesh[:, mesh[1] != 4]  # node 4 has no incoming mesh edge: aggregates to 0
    contact = torch.stack([torch.randint(0, n, (n * 2,)), torch.arange(n).repeat_interleave(2)])
    mask = torch.rand(n * 2) > 0.4
    e_mesh, e_contact = torch.randn(mesh.size(1), d), torch.randn(contact.size(1), d)
    ref = conv(x, mesh, e_mesh, contact, e_contact, mask)
    slotted_mesh = SlottedEdgeIndex.build(mesh, n)
    table = torch.where(mask.view(n, 2), torch.arange(2 * n).view(n, 2), -1)  # row-major slots
    slotted_contact = SlottedEdgeIndex(contact, table)
    built = SlottedEdgeIndex.build(contact, n, mask)  # the same edges per target, packed to the left
    for contact_edges in (slotted_contact, built):
        out = conv(x, slotted_mesh, e_mesh, contact_edges, e_contact, mask)
        for a, b in zip(out, ref, strict=True):
            torch.testing.assert_close(a, b)
    inter = InterLevelConv(d, 16, aggr=aggr)
    down = torch.stack([torch.arange(n), torch.tensor([0, 0, 1, 1, 1, 2, 2, 0, 1])])  # coarse node 3: none
    xs = (x, torch.randn(4, d))
    e = torch.randn(n, d)
    for a, b in zip(inter(xs, SlottedEdgeIndex.build(down, 4), e), inter(xs, down, e), strict=True):
        torch.testing.assert_close(a, b)


def test_incoming_slots_by_hand():
    edge_index = torch.tensor([[0, 1, 2, 3], [2, 0, 2, 2]])
    slots = incoming_slots(edge_index, 4)
    assert slots.tolist() == [[1, -1, -1], [-1, -1, -1], [0, 2, 3], [-1, -1, -1]]
    masked = incoming_slots(edge_index, 4, mask=torch.tensor([True, True, False, True]))
    assert masked.tolist() == [[1, -1], [-1, -1], [0, 3], [-1, -1]]


# ---- FastRollout -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def long_run(small_sim):
    """A 50-step run of the small setting (seed 3)."""
    import dataclasses

    from torch_ampn.sim import simulate_batch

    return simulate_batch(dataclasses.replace(small_sim, num_steps=50), seeds=[3, 4])


def _surrogate(traj, hierarchy, **kwargs) -> AMPNSurrogate:
    """A small surrogate (d = 8, 3 levels: every kind of layer and a middle level) with random
    weights and real statistics. Small, so that its eager rollouts are quick; the compile time
    hardly depends on d (the quickstart's d = 32 compiles to the same kernels)."""
    torch.manual_seed(0)
    args = dict(hidden_channels=8, mlp_channels=8, num_levels=3, pre_layers=1, down_layers=1,
                solve_layers=1, post_layers=1, up_layers=1, contact_radius=12.0, contact_k=1,
                num_components=int(traj.component.max()) + 1, num_grippers=traj.num_grippers)  # fmt: skip
    s = AMPNSurrogate(**{**args, **kwargs})
    for t in range(1, traj.num_steps + 1, 5):
        s.accumulate_statistics(s.contact(step_sample(traj, t, hierarchy)))
    s.freeze_statistics()
    return s.eval()


def _plain(surrogate, traj, hierarchy, seed=3):
    g = torch.Generator().manual_seed(seed)
    return rollout(lambda d: surrogate.predict_residual(d, g), traj, hierarchy, surrogate.contact)


@pytest.fixture(scope="module")
def hierarchy(long_run):
    return HierarchyCache(None, max_levels=3, min_coarse_nodes=4)(long_run[0])


@pytest.mark.parametrize(
    "candidates", ["auto", ("search", "verlet", "dense"), ("patches", "patches", "dense")]
)
def test_fast_rollout_equals_the_plain_rollout(long_run, hierarchy, candidates):
    traj = long_run[0]
    s = _surrogate(traj, hierarchy)
    ref = _plain(s, traj, hierarchy)
    assert (ref[-1] - ref[0]).abs().max() > 1.0  # the plies move: the comparison means something
    fast = FastRollout(s, hierarchy, compile=False, candidates=candidates)
    out = fast([traj], [torch.Generator().manual_seed(3)])[0]
    assert out.shape == ref.shape == (51, traj.num_nodes, 3)
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=0)


def test_fast_rollout_of_a_stack_encoded_model_with_spare_components(long_run, hierarchy):
    """``component_encoding="stack"`` and more components than the mesh has (a family's model)."""
    traj = long_run[0]
    s = _surrogate(traj, hierarchy, component_encoding="stack", num_components=8)
    ref = _plain(s, traj, hierarchy)
    out = FastRollout(s, hierarchy, compile=False)([traj], [torch.Generator().manual_seed(3)])[0]
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=0)


def test_fast_rollout_of_a_model_with_prior_features(long_run, hierarchy):
    """The prior's offset and step enter the fast path's features as the plain path's."""
    traj = long_run[0]
    g = torch.Generator().manual_seed(5)
    prior = traj.pos + 0.3 * torch.randn(traj.pos.shape, generator=g)  # a prior, wrong by 0.3 mm
    traj = dataclasses.replace(traj, prior=prior)
    s = _surrogate(traj, hierarchy, prior_features=True)
    ref = _plain(s, traj, hierarchy)
    out = FastRollout(s, hierarchy, compile=False)([traj], [torch.Generator().manual_seed(3)])[0]
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=0)
    other = _plain(s, dataclasses.replace(traj, prior=prior + 1.0), hierarchy)
    assert (other - ref).abs().max() > 1e-3  # the prior matters: the comparison means something
    with pytest.raises(ValueError, match=r"trajectories \[0\] have none"):
        FastRollout(s, hierarchy, compile=False)([dataclasses.replace(traj, prior=None)])


def test_surrogate_predictor_gives_the_prior_and_leaves_the_callers_trajectories_alone(long_run, hierarchy):
    """The design predictor of a prior-reading surrogate: the plain rollout with the baseline's prior."""
    from torch_ampn.baselines import MeanTrajectory
    from torch_ampn.design import surrogate_predictor

    traj, mean = long_run[0], MeanTrajectory().fit(long_run)
    with_prior = dataclasses.replace(traj, prior=mean.predict(traj))
    s = _surrogate(with_prior, hierarchy, prior_features=True)
    out = surrogate_predictor(s, hierarchy, prior=mean, compile=False, seed=3)([traj])[0]
    ref = _plain(s, with_prior, hierarchy, seed=3)
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=0)
    assert traj.prior is None  # the predictor worked on a copy
    with pytest.raises(ValueError, match="give the fitted prior baseline"):
        surrogate_predictor(s, hierarchy)


#: The compiled tests' surrogates, the fewest ops that hold the graph each test checks (a compile
#: costs about a minute per step graph and layer count on 2 cores, whatever d): the fused step
#: (features, contact slots, an intra-level layer and the update in one graph) on a flat network
#: of one layer; the network compiled apart on the two inter-level stacks of a 2-level V-cycle.
FUSED = dict(num_levels=1, pre_layers=0, post_layers=0)
APART = dict(num_levels=2, pre_layers=0, solve_layers=0, post_layers=0)


@pytest.mark.slow
@pytest.mark.xdist_group("compiled_fused")  # with test_many_fast_rollouts_...[fused]: its graph, cached
@pytest.mark.usefixtures("unoptimised_kernels")
def test_compiled_fast_rollout_equals_the_plain_rollout(long_run, hierarchy, monkeypatch):
    monkeypatch.delenv("TORCHINDUCTOR_CPP_WRAPPER", raising=False)  # the default rule (conftest sets 0)
    traj = long_run[0]
    s = _surrogate(traj, hierarchy, **FUSED)
    ref = _plain(s, traj, hierarchy)
    out = rollout(s, traj, hierarchy, fast=True, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=0)
    runner = cached_fast_rollout(s, hierarchy)
    assert runner.compiled  # it did compile (no silent fallback on this machine)
    assert runner.cpp_wrapper  # a small step: its wrapper is C++


@pytest.mark.slow
@pytest.mark.xdist_group("compiled_apart")  # with test_many_fast_rollouts_...[apart]: its graphs, cached
@pytest.mark.usefixtures("unoptimised_kernels")
def test_compiled_robin_fast_rollout_with_the_python_wrapper_equals_the_plain_rollout(long_run, hierarchy):
    """K > 1 (inputs and network compiled apart) with the Python wrapper, what a large step gets."""
    traj = long_run[0]
    robin = _surrogate(traj, hierarchy, diffusion_steps=3, **APART)
    g = torch.Generator().manual_seed(3)
    ref = rollout(lambda d: robin.predict_residual(d, g), traj, hierarchy, robin.contact, num_steps=4)
    python_wrapper = FastRollout(robin, hierarchy, cpp_wrapper=False)
    out = python_wrapper([traj], [torch.Generator().manual_seed(3)], num_steps=4)[0]
    assert python_wrapper.compiled and not python_wrapper.cpp_wrapper
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=0)


def test_cpp_wrapper_by_default_only_where_the_step_is_small(long_run, hierarchy, monkeypatch):
    monkeypatch.delenv("TORCHINDUCTOR_CPP_WRAPPER", raising=False)
    s = _surrogate(long_run[0], hierarchy)
    n, d = long_run[0].num_nodes, s.model.hidden_channels
    fits = FastRollout.CPP_WRAPPER_LIMIT // (n * d)  # the largest batch within the limit
    assert FastRollout(s, hierarchy, batch_size=fits).cpp_wrapper  # nothing compiles before a call
    assert not FastRollout(s, hierarchy, batch_size=fits + 1).cpp_wrapper
    assert FastRollout(s, hierarchy, batch_size=fits + 1, cpp_wrapper=True).cpp_wrapper
    assert not FastRollout(s, hierarchy, compile=False).cpp_wrapper
    # Inductor's environment variable overrides the rule, an explicit argument overrides both
    monkeypatch.setenv("TORCHINDUCTOR_CPP_WRAPPER", "0")
    assert not FastRollout(s, hierarchy, batch_size=fits).cpp_wrapper
    assert FastRollout(s, hierarchy, batch_size=fits, cpp_wrapper=True).cpp_wrapper
    monkeypatch.setenv("TORCHINDUCTOR_CPP_WRAPPER", "1")
    assert FastRollout(s, hierarchy, batch_size=fits + 1).cpp_wrapper
    assert not FastRollout(s, hierarchy, batch_size=fits + 1, cpp_wrapper=False).cpp_wrapper


def test_a_batch_of_settings_equals_its_settings_one_by_one(long_run, hierarchy):
    s = _surrogate(long_run[0], hierarchy, diffusion_steps=3)  # ROBIN: several noise draws per step
    trajs = [long_run[0], long_run[1], long_run[0]]
    batch = FastRollout(s, hierarchy, batch_size=4, compile=False)
    out = batch(trajs, [torch.Generator().manual_seed(i) for i in range(3)], num_steps=12)
    assert out.shape == (3, 13, long_run[0].num_nodes, 3)
    single = FastRollout(s, hierarchy, batch_size=1, compile=False)
    for i, traj in enumerate(trajs):
        one = single([traj], [torch.Generator().manual_seed(i)], num_steps=12)[0]
        # equal up to fp32 rounding: batching changes the products' blocking, and one ulp of a
        # position of ~150 mm is 1.5e-5 mm (AVX2 CPUs round differently from AVX-512 ones here)
        torch.testing.assert_close(out[i], one, atol=1e-4, rtol=0)
    assert not torch.allclose(out[0], out[2])  # other noise, other rollout


def test_failed_compile_warns_and_runs_eagerly(long_run, hierarchy, monkeypatch):
    traj = long_run[0]
    s = _surrogate(traj, hierarchy)

    def broken(fn, **kwargs):
        def call(*args, **kw):
            raise RuntimeError("no C++ compiler")

        return call

    monkeypatch.setattr(torch, "compile", broken)
    fast = FastRollout(s, hierarchy, compile=True)
    with pytest.warns(RuntimeWarning, match="runs eagerly"):
        out = fast([traj], [torch.Generator().manual_seed(3)], num_steps=10)[0]
    assert not fast.compiled
    torch.testing.assert_close(out, _plain(s, traj, hierarchy)[:11], atol=1e-4, rtol=0)


def test_settings_without_a_fast_path_take_the_plain_path(long_run, hierarchy):
    traj = long_run[0]
    s = _surrogate(traj, hierarchy, contact_mode="radius")
    with pytest.warns(RuntimeWarning, match="taking the plain path"):
        out = rollout(s, traj, hierarchy, fast=True, generator=torch.Generator().manual_seed(3), num_steps=5)
    torch.testing.assert_close(out, _plain(s, traj, hierarchy)[:6])


def test_rollout_surrogate_is_the_one_choice_of_path(long_run, hierarchy):
    """Fast where the settings allow it (batched, the plain rollout's result), else plain with a warning."""
    from torch_ampn.rollout import rollout_surrogate

    s = _surrogate(long_run[0], hierarchy)
    trajs = list(long_run)
    gens = [torch.Generator().manual_seed(3) for _ in trajs]
    fast = rollout_surrogate(s, trajs, hierarchy, gens, batch_size=2, compile=False, num_steps=10)
    for one, out in zip(trajs, fast, strict=True):
        torch.testing.assert_close(out, _plain(s, one, hierarchy)[:11], atol=1e-4, rtol=0)
    plain = rollout_surrogate(s, trajs[:1], hierarchy, [torch.Generator().manual_seed(3)], fast=False)
    torch.testing.assert_close(plain[0], _plain(s, trajs[0], hierarchy), atol=0, rtol=0)
    radius = _surrogate(long_run[0], hierarchy, contact_mode="radius")
    with pytest.warns(RuntimeWarning, match="contact mode 'radius'.*taking the plain path"):
        out = rollout_surrogate(radius, trajs[:1], hierarchy, [torch.Generator().manual_seed(3)], num_steps=5)
    torch.testing.assert_close(out[0], _plain(radius, trajs[0], hierarchy)[:6], atol=0, rtol=0)
    with pytest.raises(ValueError, match="got 1 generators for 2 trajectories"):
        rollout_surrogate(s, trajs, hierarchy, gens[:1])


def test_static_contact_fast_path(long_run, hierarchy):
    traj = long_run[0]
    s = _surrogate(traj, hierarchy, contact_positions="initial")
    out = FastRollout(s, hierarchy, compile=False)([traj], [torch.Generator().manual_seed(3)], num_steps=10)[
        0
    ]
    torch.testing.assert_close(out, _plain(s, traj, hierarchy)[:11], atol=1e-4, rtol=0)


def test_fast_rollout_refuses_another_mesh(long_run, hierarchy):
    s = _surrogate(long_run[0], hierarchy)
    fast = FastRollout(s, hierarchy, compile=False)
    other = small_trajectory()
    with pytest.raises(ValueError, match="nodes; this FastRollout's mesh has"):
        fast([other])
    with pytest.raises(ValueError, match="expected 1 to 1 trajectories"):
        fast([long_run[0], long_run[1]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast([long_run[0]], num_steps=2)  # no generator: the default one, no warning


def test_rollout_settings_and_batched_predict_equal_single_rollouts(
    long_run, hierarchy, tmp_path, monkeypatch
):
    from torch_ampn.rollout import rollout_settings
    from torch_ampn.training import NextStepLightningModule
    from torch_ampn.training.items import RolloutItem

    traj = long_run[0]
    s = _surrogate(traj, hierarchy)
    trajs = [long_run[0], long_run[1], long_run[1]]
    out = rollout_settings(s, trajs, hierarchy, batch_size=2, compile=False)  # batches of 2, 1 (padded)
    for i, one in enumerate(trajs):
        ref = FastRollout(s, hierarchy, compile=False)([one], [torch.Generator().manual_seed(i)])[0]
        # fp32 rounding of other blockings, grown over 50 steps: 1e-5 mm on a Xeon, 8e-5 mm on
        # an AVX2-only EPYC; a setting mixed up with another would be off by millimetres
        torch.testing.assert_close(out[i], ref, atol=5e-4, rtol=0)
    # the module's predict_step: a list of items is one batch, the same as item by item
    args = dict(hidden_channels=8, mlp_channels=8, num_levels=3, pre_layers=1, down_layers=1,
                solve_layers=1, post_layers=1, up_layers=1, contact_radius=12.0, contact_k=1,
                output_dir=str(tmp_path), num_components=s.num_components, num_grippers=s.num_grippers,
                export_xdmf=False)  # fmt: skip
    module = NextStepLightningModule(**args)
    module.surrogate.load_state_dict(s.state_dict())
    module.surrogate.freeze_statistics()
    module.eval()
    items = [RolloutItem(i, f"setting{i}", t, hierarchy) for i, t in enumerate(trajs)]
    # batching is what this checks, not compiling (the tests above): the fast path runs eagerly
    eager_fast_rollout(monkeypatch)
    with torch.no_grad():
        together = module.predict_step(items, 0)
        alone = [module.predict_step(item, 0) for item in items]
    runners = module.surrogate._fast_rollouts.values()  # the surrogate's own cache
    assert runners and all(not r.compiled for r in runners)
    # other blockings round differently, and 50 autoregressive steps grow that (as above)
    for a, b in zip(together, alone, strict=True):
        torch.testing.assert_close(a, b, atol=5e-4, rtol=0)
    assert sorted(p.name for p in (tmp_path / "predict").glob("*.png")) == [
        f"setting{i}.png" for i in range(3)
    ]


@pytest.mark.slow
@pytest.mark.parametrize(
    "diffusion_steps, cpp_wrapper",
    [
        pytest.param(1, None, id="fused", marks=pytest.mark.xdist_group("compiled_fused")),
        pytest.param(3, False, id="apart", marks=pytest.mark.xdist_group("compiled_apart")),
    ],
)
@pytest.mark.usefixtures("unoptimised_kernels")
def test_many_fast_rollouts_each_keep_their_compiled_step(
    long_run, hierarchy, monkeypatch, diffusion_steps, cpp_wrapper
):
    """Dynamo caches compiled code per code object and stops compiling one after ``recompile_limit``
    entries: the steps of many FastRollout objects (a design study over many meshes) must not share one.

    The fused step (C++ wrapper) and the inputs and network compiled apart (Python wrapper):
    the graphs of the two compiled tests above, found in Inductor's cache."""
    import torch._dynamo

    monkeypatch.setattr(torch._dynamo.config, "recompile_limit", 1)
    monkeypatch.setattr(torch._dynamo.config, "fail_on_recompile_limit_hit", True)  # raise, not run eagerly
    monkeypatch.delenv("TORCHINDUCTOR_CPP_WRAPPER", raising=False)
    traj = long_run[0]
    g = torch.Generator
    layers = FUSED if diffusion_steps == 1 else APART
    s = _surrogate(traj, hierarchy, diffusion_steps=diffusion_steps, **layers)
    ref = FastRollout(s, hierarchy, compile=False)([traj], [g().manual_seed(3)], num_steps=3)[0]
    for _ in range(2):
        fast = FastRollout(s, hierarchy, cpp_wrapper=cpp_wrapper)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no "runs eagerly" fallback
            out = fast([traj], [g().manual_seed(3)], num_steps=3)[0]
        assert fast.compiled
        torch.testing.assert_close(out, ref, atol=1e-4, rtol=0)
