"""Design search: the known optimum of an analytic stand-in, the settings space, verification end to end."""

import numpy as np
import pytest
import torch

from torch_ampn.design import (
    SettingsSpace,
    baseline_predictor,
    measure_weights,
    parameter_map,
    search_settings,
    settings_objective,
    settings_trajectories,
    simulator_predictor,
    spearman_ceiling,
    verify_choice,
)
from torch_ampn.design.measures import part_quality
from torch_ampn.sim import simulate_batch
from torch_ampn.sim.simulate import sample_process


def test_the_search_finds_the_optimum_of_an_analytic_stand_in():
    space = SettingsSpace(2, (0.15, 0.85), (0.0, 100.0))
    target = np.array([0.3, 0.7, 80.0, 12.0])
    scale = np.array([0.7, 0.7, 100.0, 100.0])
    calls = []

    def objective(x):  # [M, 4] -> [M], a bowl with its minimum at `target`, plus a ripple
        calls.append(len(x))
        z = (x - target) / scale
        return (z**2).sum(1) + 0.01 * (1 - np.cos(8 * np.pi * z)).sum(1)

    result = search_settings(objective, space.bounds, maxiter=40, popsize=10, seed=0)
    assert len(calls) == 41 and set(calls) == {40}  # one batched call per generation
    assert len(result.values) == sum(calls) and result.history == sorted(result.history, reverse=True)
    assert np.all(np.abs(result.best - target) / scale < 0.02)
    assert result.best_value == pytest.approx(float(objective(result.best[None])[0]))
    top, values = result.top(3)
    assert np.array_equal(top[0], result.best) and np.all(np.diff(values) >= 0)


def test_the_parameter_map_holds_the_objective_on_its_grid():
    space = SettingsSpace(2, (0.15, 0.85), (0.0, 100.0))
    best = np.array([0.3, 0.7, 80.0, 12.0])

    def objective(x):  # [M, 4] -> [M]
        return x[:, 0] * 1000 + x[:, 3] + x[:, 1] * x[:, 2]

    grid = parameter_map(objective, space, best, (0, 3), points=4)
    assert grid["axes"] == ["position_0", "force_1"]
    np.testing.assert_allclose(grid["a"], np.linspace(0.15, 0.85, 4))
    i, j = 2, 1  # by hand: position_0 = a[2], force_1 = b[1], the others at best
    expected = grid["a"][i] * 1000 + grid["b"][j] + 0.7 * 80.0
    assert grid["values"].shape == (4, 4) and grid["values"][i, j] == pytest.approx(expected)


def test_the_settings_space_of_a_config(small_sim):
    space = SettingsSpace.from_config(small_sim)
    assert space.names == ["position_0", "position_1", "force_0", "force_1"]
    x = space.sample(50, seed=3)
    lo, hi = np.array(space.bounds).T
    assert x.shape == (50, 4) and np.all((x >= lo) & (x <= hi))
    assert space.split(x[:1]) == [(x[0, :2].tolist(), x[0, 2:].tolist())]
    with pytest.raises(ValueError, match="need 4 values each"):
        space.split(np.zeros((1, 3)))
    with pytest.raises(ValueError, match="measure must be among"):
        settings_objective(lambda trajs: [], small_sim, "smoothness")


def test_measure_weights_of_a_name_and_of_a_weighted_sum():
    assert measure_weights("wrinkle_rms") == {"wrinkle_rms": 1.0}
    assert measure_weights({"draw_in_mean": 2, "shear_max": 0.5}) == {"draw_in_mean": 2.0, "shear_max": 0.5}
    bad_ones = [("smoothness", "smoothness"), ({"wrinkle_rms": 1, "waviness": 1}, "waviness"), ({}, "none")]
    for bad, named in bad_ones:
        with pytest.raises(ValueError, match=f"measure must be among .*{named}"):
            measure_weights(bad)


def test_explicit_settings_simulate_as_their_seed_does(quick_sim):
    where, force = sample_process(quick_sim, 7)
    by_seed = simulate_batch(quick_sim, [7])[0]
    by_settings = simulate_batch(quick_sim, settings=[(where, force)])[0]
    assert torch.equal(by_seed.pos, by_settings.pos)
    assert by_settings.meta["gripper_edge_fraction"] == where.tolist()
    with pytest.raises(ValueError, match="gripper_forces must be >= 0 N"):
        simulate_batch(quick_sim, settings=[(where, [-1.0, 2.0])])


def test_verify_with_the_simulator_as_its_own_predictor(quick_sim):
    """Predicted == simulated (eager, deterministic): Spearman 1, the rank counted by hand."""
    chosen = np.array([0.5, 0.5, 50.0, 50.0])
    other = np.array([0.2, 0.8, 90.0, 10.0])
    check = verify_choice(
        quick_sim, chosen, simulator_predictor(quick_sim), "draw_in_mean", num_random=3, seed=2,
        alternatives={"other": other},
    )  # fmt: skip
    alt = check.alternatives["other"]
    assert alt["predicted"] == alt["simulated"] and np.array_equal(alt["settings"], other)
    assert alt["rank"] == 1 + int((check.random_simulated < alt["simulated"]).sum())
    assert len(check.simulated_measures["wrinkle_rms"]) == 4  # the chosen and the random ones only
    assert check.chosen_predicted == check.chosen_simulated
    np.testing.assert_array_equal(check.random_predicted, check.random_simulated)
    assert check.spearman == pytest.approx(1.0)
    assert check.rank == 1 + int((check.random_simulated < check.chosen_simulated).sum())
    assert check.to_dict()["percentile"] == (check.rank - 1) / 4
    with pytest.raises(ValueError, match="at least 2 random settings"):
        verify_choice(quick_sim, chosen, simulator_predictor(quick_sim), "draw_in_mean", num_random=1)


@pytest.mark.slow
def test_runs_judge_each_setting_by_its_mean_over_perturbed_simulations(quick_sim):
    """Run 0 is the unperturbed simulator, run k the simulator from its own moved start; mean by hand."""
    from scipy.stats import spearmanr

    chosen = np.array([0.5, 0.5, 50.0, 50.0])
    check = verify_choice(
        quick_sim, chosen, simulator_predictor(quick_sim), "draw_in_mean", num_random=3, seed=2,
        runs=3, repeat=1e-3,
    )  # fmt: skip
    runs = check.run_measures["draw_in_mean"]  # [3, 4]
    assert check.runs == 3 and runs.shape == (3, 4) and check.run_objective.shape == (3, 4)
    np.testing.assert_array_equal(runs[0], check.predicted_measures["draw_in_mean"])  # eager: equal
    np.testing.assert_allclose(check.simulated_measures["draw_in_mean"], runs.mean(axis=0))
    assert check.chosen_simulated == pytest.approx(runs[:, 0].mean())
    assert check.rank == 1 + int((runs[:, 1:].mean(0) < runs[:, 0].mean()).sum())
    # run 2 of the chosen setting (index 0 of 4 settings): seed 2 * 4, moved by 1e-3 mm, judged
    # against the part's unmoved start
    where, force = [float(v) for v in chosen[:2]], [float(v) for v in chosen[2:]]
    again = simulate_batch(quick_sim, [8], settings=[(where, force)], perturbation=1e-3)[0]
    part = settings_trajectories(quick_sim, SettingsSpace.from_config(quick_sim), chosen[None])[0]
    assert part_quality(part, again.pos[-1])["draw_in_mean"] == pytest.approx(runs[2, 0], rel=1e-9)
    assert not np.array_equal(runs[1], runs[2])  # each run its own perturbation
    pairs = [spearmanr(runs[i, 1:], runs[j, 1:]).statistic for i, j in [(0, 1), (0, 2), (1, 2)]]
    assert check.repeat_spearman_by_measure["draw_in_mean"] == pytest.approx(np.mean(pairs))
    assert check.repeat == 1e-3 and check.to_dict()["runs"] == 3
    with pytest.raises(ValueError, match="runs must be >= 1"):
        verify_choice(quick_sim, chosen, simulator_predictor(quick_sim), "draw_in_mean", runs=0)


def test_the_spearman_ceiling_by_hand():
    """One run: sqrt(r); R runs: sqrt(R r / (1 + (R - 1) r)) (Spearman-Brown); none without a positive r."""
    assert spearman_ceiling(0.25) == pytest.approx(0.5)
    assert spearman_ceiling(0.25, runs=3) == pytest.approx(np.sqrt(0.75 / 1.5))
    assert spearman_ceiling(1.0, runs=4) == pytest.approx(1.0)
    assert np.isnan(spearman_ceiling(0.0)) and np.isnan(spearman_ceiling(float("nan")))


def test_a_baseline_predictor_gives_the_last_state(small_runs, small_sim):
    from torch_ampn.baselines import MeanTrajectory

    mean = MeanTrajectory().fit(small_runs)
    trajs = settings_trajectories(
        small_sim, SettingsSpace.from_config(small_sim), np.array([[0.4, 0.6, 10.0, 90.0]])
    )
    (predicted,) = baseline_predictor(mean)(trajs)
    torch.testing.assert_close(predicted, mean.predict(trajs[0]))
    value = settings_objective(baseline_predictor(mean), small_sim, {"draw_in_mean": 2.0, "shear_max": 0.5})
    assert value(np.array([[0.4, 0.6, 10.0, 90.0]])).shape == (1,)


def test_refinement_descends_to_the_bowls_minimum_and_never_climbs():
    from torch_ampn.design import refine_settings

    space = SettingsSpace(2, (0.15, 0.85), (0.0, 100.0))
    target = np.array([0.3, 0.7, 80.0, 12.0])
    scale = np.array([0.7, 0.7, 100.0, 100.0])
    calls = []

    def objective(x):  # a smooth bowl, minimum at `target`
        calls.append(len(x))
        return (((x - target) / scale) ** 2).sum(1)

    start = np.array([0.6, 0.4, 40.0, 60.0])
    result = refine_settings(objective, space.bounds, start, steps=30)
    assert set(calls) <= {9, 3}  # one batch of 2 D + 1 differences, one of 3 step lengths per step
    assert result.evaluations == sum(calls)
    assert np.all(np.diff(result.history) < 0) and result.best_value == result.history[-1]
    assert result.best_value < 0.01 * result.start_value
    assert np.all(np.abs(result.best - target) / scale < 0.05)
    # at a face of the box the step is clipped and stays inside it
    edge = refine_settings(objective, space.bounds, np.array([0.15, 0.85, 100.0, 0.0]), steps=3)
    lo, hi = np.array(space.bounds).T
    assert np.all((edge.best >= lo) & (edge.best <= hi)) and edge.best_value < edge.start_value
    # at the minimum nothing improves: the start comes back
    still = refine_settings(objective, space.bounds, target, steps=3)
    assert np.array_equal(still.best, target) and still.steps == 0 and still.improvement == 0.0
