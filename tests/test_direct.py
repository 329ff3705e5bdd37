"""The direct model: (initial state, settings) -> displacement at every step, without a rollout."""

import dataclasses

import numpy as np
import pytest
import torch

from torch_ampn.data import DirectDataset, HierarchyCache, TrajectoryDataset
from torch_ampn.forming.direct import DirectSurrogate, ModeDecoder, TimeEncoding
from torch_ampn.rollout.direct import predict_direct
from torch_ampn.rollout.surrogate import rollout, rollout_surrogate

SMALL = dict(
    hidden_channels=16, mlp_channels=16, num_levels=2, pre_layers=1, down_layers=1, solve_layers=1,
    post_layers=1, up_layers=1, contact_radius=3.0, contact_k=1,
)  # fmt: skip


def _fitted(data_dir, **kwargs) -> tuple[DirectSurrogate, DirectDataset]:
    torch.manual_seed(0)
    model = DirectSurrogate(**{**SMALL, **kwargs})
    train = DirectDataset(data_dir, "train", max_levels=2, transform=model.contact)
    for i in range(len(train)):
        model.accumulate_statistics(train[i])
    model.freeze_statistics()
    return model, train


def _hierarchy(traj):
    return HierarchyCache(None, max_levels=2)(traj)


def test_the_mean_base_and_the_target_scale_match_a_float64_reference(tiny_data):
    model, train = _fitted(tiny_data)
    disp = torch.stack([t.pos[1:].double() - t.pos[0].double() for t in train.trajectories])  # [K, T, N, 3]
    mean = disp.mean(0)  # [T, N, 3]
    steps = torch.arange(1, disp.size(1) + 1)
    base = model._base(train[0], steps)  # [N, T, 3]
    torch.testing.assert_close(base.double(), mean.transpose(0, 1), atol=1e-5, rtol=1e-5)
    ply = train.trajectories[0].ply_mask
    spread = (disp - mean)[:, :, ply].reshape(-1, 3)  # departures of every ply entry
    torch.testing.assert_close(model.target_norm.std, spread.square().mean(0).sqrt(), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("target_scale", ["step", "node_step"])
def test_step_scales_are_the_float64_spread_about_the_mean_and_scale_output_and_loss(tiny_data, target_scale):
    model, train = _fitted(tiny_data, target_scale=target_scale)
    disp = torch.stack([t.pos[1:].double() - t.pos[0].double() for t in train.trajectories])  # [K, T, N, 3]
    var = (disp - disp.mean(0)).square().mean(0)  # [T, N, 3], population variance over the samples
    if target_scale == "step":
        var = var.mean(1, keepdim=True).expand_as(var)  # every node of a step alike
    floor = 1e-2 * var.mean((0, 1)).sqrt()
    expected = (var + floor.square()).sqrt().transpose(0, 1)  # [N, T, 3]
    steps = torch.arange(1, disp.size(1) + 1)
    sample = train[0]
    scale = model._departure_scale(sample, steps)
    torch.testing.assert_close(scale.double(), expected, rtol=1e-5, atol=1e-9)
    if target_scale == "step":  # early steps, where the settings have moved little, get a small scale
        assert scale[0, 0].norm() < scale[0, -1].norm()
    # the output is in units of the scale: an output of ones moves every node by its scale
    model._decode = lambda data, h, t, mask=None, base=None: torch.ones(  # noqa: ARG005
        int(mask.sum()) if mask is not None else data["l0"].num_nodes, t.numel(), 3
    )
    pred = model.predict_displacement(sample, disp.size(1))
    torch.testing.assert_close(pred, model._base(sample, steps) + scale)
    # ... and the loss is the MSE of (output - departure / scale) over the ply nodes
    ply = sample["l0"].ply_mask
    departure = (sample["l0"].displacement.double() - model._base(sample, steps).double())[ply]
    reference = (1 - departure / expected[ply]).square().mean()
    torch.testing.assert_close(model.loss(sample).double(), reference, rtol=1e-4, atol=1e-7)


def test_step_scales_need_the_mean_base():
    with pytest.raises(ValueError, match="target_scale must be one of"):
        DirectSurrogate(base="initial", target_scale="step")
    with pytest.raises(ValueError, match="target_scale must be one of"):
        DirectSurrogate(target_scale="per_node")


def test_a_zero_output_predicts_the_mean_training_trajectory_and_the_tools_prescribed_motion(tiny_data):
    model, train = _fitted(tiny_data)
    last = model.decoder.rest[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    traj = TrajectoryDataset(tiny_data, "test")[0]
    (pred,) = predict_direct(model.eval(), [traj], _hierarchy(traj))
    mean = torch.stack([t.pos.float() - t.pos[0].float() for t in train.trajectories]).mean(0)
    ply = traj.ply_mask
    torch.testing.assert_close(pred[:, ply], traj.pos[0, ply].float() + mean[:, ply], atol=1e-4, rtol=0)
    torch.testing.assert_close(pred[:, ~ply], traj.pos[:, ~ply].float())


def test_batches_predict_what_single_settings_do_and_the_future_is_never_read(tiny_data):
    model, _ = _fitted(tiny_data)
    trajs = [TrajectoryDataset(tiny_data, s)[0] for s in ("test", "val", "train")]
    h = _hierarchy(trajs[0])
    alone = [predict_direct(model.eval(), [t], h)[0] for t in trajs]
    together = predict_direct(model, trajs, h, batch_size=2)
    for a, b in zip(alone, together, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    scrambled = trajs[0].pos.clone()
    scrambled[1:, trajs[0].ply_mask] += 100.0  # the ply's future: never an input
    (same,) = predict_direct(model, [dataclasses.replace(trajs[0], pos=scrambled)], h)
    torch.testing.assert_close(same[:, trajs[0].ply_mask], alone[0][:, trajs[0].ply_mask])
    (last,) = predict_direct(model, [trajs[0]], h, final=True)  # the formed part alone
    torch.testing.assert_close(last, alone[0][-1], atol=1e-5, rtol=1e-5)
    # rollout_surrogate, the path of test/predict/design, takes the direct one
    (routed,) = rollout_surrogate(model, [trajs[0]], h, [None], batch_size=4)
    torch.testing.assert_close(routed, alone[0])
    # ... and so does rollout, the tour's call, on either path, whole or cut short
    torch.testing.assert_close(rollout(model, trajs[0], h, fast=True), alone[0])
    torch.testing.assert_close(rollout(model, trajs[0], h, num_steps=2), alone[0][:3])
    from torch_ampn.design import surrogate_predictor

    finals = surrogate_predictor(model, h, batch_size=2, final=True)(trajs)  # the design search's path
    for a, f in zip(alone, finals, strict=True):
        assert f.shape == (1, *a.shape[1:])
        torch.testing.assert_close(f[0], a[-1], atol=1e-5, rtol=1e-5)


def test_settings_of_one_initial_state_share_its_contact_search_and_predict_as_alone(tiny_data):
    model, _ = _fitted(tiny_data)
    traj = TrajectoryDataset(tiny_data, "test")[0]
    h = _hierarchy(traj)
    forces = [traj.gripper_force * f for f in (0.5, 1.0, 2.0)]
    lifted = traj.pos.clone()
    lifted[:, traj.ply_mask] += torch.tensor([0.0, 0.0, 50.0])  # another initial state: other contacts
    trajs = [dataclasses.replace(traj, gripper_force=f) for f in forces]
    trajs.insert(2, dataclasses.replace(traj, pos=lifted))
    searches = []
    search = model.contact.forward

    def counted(data):
        searches.append(1)
        return search(data)

    model.contact.forward = counted
    together = predict_direct(model.eval(), trajs, h, batch_size=4)
    assert len(searches) == 3  # the first, the lifted one, the first's again after it
    del model.contact.forward
    for t, b in zip(trajs, together, strict=True):
        torch.testing.assert_close(b, predict_direct(model, [t], h)[0], atol=1e-5, rtol=1e-5)
    assert (together[2] - together[1]).abs().max() > 1e-3  # the lifted state is not read as the first


@pytest.mark.parametrize("layers", [3, 4])
def test_the_mode_decoder_is_a_sum_of_modes_times_coefficients_of_each_sample(layers):
    """Against a float64 loop over nodes, steps and modes, with two samples in one batch."""
    torch.manual_seed(0)
    dec = ModeDecoder(latent_channels=5, settings_channels=4, modes=3, hidden_channels=8, layers=layers)
    dec = dec.double()
    assert sum(isinstance(m, torch.nn.Linear) for m in dec.branch.rest) == layers - 1
    torch.nn.init.normal_(dec.branch.rest[-1].weight)  # it starts at zero
    h, settings = torch.randn(6, 5, dtype=torch.float64), torch.randn(2, 4, dtype=torch.float64)
    t, batch = torch.tensor([0.25, 1.0], dtype=torch.float64), torch.tensor([0, 0, 0, 1, 1, 1])
    out = dec(h, settings, t, batch)  # [6, 2, 3]
    norm = torch.nn.functional.layer_norm(h, (5,), dec.norm.weight, dec.norm.bias)
    for i in range(6):
        phi = (dec.trunk.weight @ norm[i] + dec.trunk.bias).reshape(3, 3)  # [K, 3]
        for j in range(2):
            freq = dec.branch.time.frequencies
            gamma = torch.cat([t[j : j + 1], (freq * t[j]).sin(), (freq * t[j]).cos()])
            hidden = dec.branch.lin_node(settings[batch[i]]) + dec.branch.lin_time.weight @ gamma
            coef = dec.branch.rest(hidden)  # [K]
            torch.testing.assert_close(out[i, j], (coef[:, None] * phi).sum(0))
    torch.testing.assert_close(dec(h[3:], settings[1:], t), out[3:])  # one sample, no batch vector


def test_space_time_modes_are_modes_of_node_and_time_times_coefficients_of_the_settings():
    """``space_time=True`` against a float64 loop, with two samples in one batch."""
    torch.manual_seed(0)
    dec = ModeDecoder(5, settings_channels=4, modes=3, hidden_channels=8, space_time=True).double()
    torch.nn.init.normal_(dec.branch[-1].weight)  # it starts at zero
    h, settings = torch.randn(6, 5, dtype=torch.float64), torch.randn(2, 4, dtype=torch.float64)
    t, batch = torch.tensor([0.25, 1.0], dtype=torch.float64), torch.tensor([0, 0, 0, 1, 1, 1])
    out = dec(h, settings, t, batch)  # [6, 2, 3]
    trunk = dec.trunk
    norm = torch.nn.functional.layer_norm(h, (5,), trunk.norm.weight, trunk.norm.bias)
    silu = torch.nn.functional.silu
    for i in range(6):
        s = settings[batch[i]]
        w = [m for m in dec.branch if isinstance(m, torch.nn.Linear)]
        coef = w[2].weight @ silu(w[1].weight @ silu(w[0].weight @ s + w[0].bias) + w[1].bias) + w[2].bias
        for j in range(2):
            freq = trunk.time.frequencies
            gamma = torch.cat([t[j : j + 1], (freq * t[j]).sin(), (freq * t[j]).cos()])
            phi = trunk.rest(trunk.lin_node(norm[i]) + trunk.lin_time.weight @ gamma).reshape(3, 3)  # [K, 3]
            torch.testing.assert_close(out[i, j], (coef[:, None] * phi).sum(0))
    torch.testing.assert_close(dec(h[3:], settings[1:], t), out[3:])  # one sample, no batch vector


def test_mode_decoder_files_of_the_older_parameter_names_load():
    torch.manual_seed(0)
    dec = ModeDecoder(latent_channels=5, settings_channels=4, modes=3, hidden_channels=8)
    torch.nn.init.normal_(dec.branch.rest[-1].weight)
    old = {}
    for key, value in dec.state_dict().items():
        for before, now in ModeDecoder.OLD_NAMES.items():
            key = key.replace(now, before) if key.startswith(now) else key
        old[key] = value
    assert "branch_time.weight" in old and "branch.3.bias" in old
    fresh = ModeDecoder(latent_channels=5, settings_channels=4, modes=3, hidden_channels=8)
    fresh.load_state_dict(old)
    h, settings, t = torch.randn(6, 5), torch.randn(1, 4), torch.tensor([0.5, 1.0])
    torch.testing.assert_close(fresh(h, settings, t), dec(h, settings, t), rtol=0, atol=0)


@pytest.mark.parametrize("space_time", [False, True])
def test_modes_start_at_zero_and_batches_still_predict_what_single_settings_do(tiny_data, space_time):
    without, _ = _fitted(tiny_data)
    # same seed: the same network before the modes
    model, train = _fitted(tiny_data, decoder_modes=4, space_time_modes=space_time)
    traj = TrajectoryDataset(tiny_data, "test")[0]
    h = _hierarchy(traj)
    torch.testing.assert_close(
        predict_direct(model.eval(), [traj], h)[0], predict_direct(without.eval(), [traj], h)[0]
    )
    torch.nn.init.normal_((model.modes.branch if space_time else model.modes.branch.rest)[-1].weight)
    trajs = [traj, *train.trajectories]
    alone = [predict_direct(model, [t], h)[0] for t in trajs]
    for a, b in zip(alone, predict_direct(model, trajs, h, batch_size=2), strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    assert (alone[0] - predict_direct(without, [traj], h)[0]).abs().max() > 1e-3  # the modes now count
    from torch_geometric.data import Batch

    loss = model.loss(Batch.from_data_list([train[0], train[1]]))  # the masked, batched path
    loss.backward()
    assert all(p.grad.abs().sum() > 0 for p in model.modes.trunk.parameters())


def test_it_learns_the_two_settings_apart(tiny_data):
    """Fitted on two settings, each prediction is far closer to its own run than the mean is."""
    model, train = _fitted(tiny_data, base="mean", hidden_channels=32, mlp_channels=32)
    from torch_geometric.data import Batch

    batch = Batch.from_data_list([train[0], train[1]])
    optimizer = torch.optim.Adam(model.parameters(), lr=5e-3)
    for _ in range(100):
        optimizer.zero_grad()
        model.loss(batch).backward()
        optimizer.step()
    h = _hierarchy(train.trajectories[0])
    trajs = list(train.trajectories)
    preds = predict_direct(model.eval(), trajs, h)
    mean = torch.stack([t.pos.float() for t in trajs]).mean(0)
    for traj, pred in zip(trajs, preds, strict=True):
        ply = traj.ply_mask
        error = (pred[1:, ply] - traj.pos[1:, ply]).norm(dim=-1).mean()
        of_mean = (mean[1:, ply] - traj.pos[1:, ply]).norm(dim=-1).mean()
        assert error < 0.5 * of_mean, (float(error), float(of_mean))


def test_the_initial_base_predicts_the_displacement_itself(tiny_data):
    model, train = _fitted(tiny_data, base="initial")
    assert model.base_norm is None and model._base(train[0], torch.arange(1, 3)) is None
    disp = torch.cat(
        [t.pos[1:, t.ply_mask].double() - t.pos[0, t.ply_mask].double() for t in train.trajectories]
    )
    # the scale only (center=False): the standard deviation of every ply displacement of every step
    reference = disp.reshape(-1, 3).std(0, correction=0)
    torch.testing.assert_close(model.target_norm.std, reference, rtol=1e-6, atol=0)


def test_a_model_file_round_trip_and_a_file_of_the_other_kind_is_refused(tiny_data, tmp_path):
    from torch_ampn.forming import AMPNSurrogate

    model, _ = _fitted(tiny_data)
    traj = TrajectoryDataset(tiny_data, "test")[0]
    h = _hierarchy(traj)
    path = model.save(tmp_path / "direct.pt", {"note": "x"})
    loaded = DirectSurrogate.load(path)
    assert loaded.statistics_frozen and loaded.meta == {"note": "x"}
    torch.testing.assert_close(
        predict_direct(loaded, [traj], h)[0], predict_direct(model.eval(), [traj], h)[0]
    )
    with pytest.raises(
        ValueError, match=r"direct\.pt: field 'kind': a DirectSurrogate model, not a AMPNSurrogate"
    ):
        AMPNSurrogate.load(path)
    from torch_ampn.forming import load_surrogate

    any_kind = load_surrogate(path)  # the class the file names
    assert type(any_kind) is DirectSurrogate and not any_kind.training
    torch.testing.assert_close(predict_direct(any_kind, [traj], h)[0], predict_direct(loaded, [traj], h)[0])
    payload = torch.load(path, weights_only=True)
    torch.save({**payload, "kind": "Foo"}, tmp_path / "foo.pt")
    with pytest.raises(ValueError, match=r"foo\.pt: field 'kind': 'Foo' is not one of"):
        load_surrogate(tmp_path / "foo.pt")


def test_the_mean_base_as_an_input_is_the_float64_mean_at_the_chosen_steps(tiny_data, tmp_path):
    """``base_input``: the nodes read the standardised mean at k steps, the decoder at the asked times."""
    model, train = _fitted(tiny_data, base_input=2)
    disp = torch.stack([t.pos[1:].double() - t.pos[0].double() for t in train.trajectories])  # [K, T, N, 3]
    mean = disp.mean(0)  # [T, N, 3]
    steps = disp.size(1)
    assert model._base_input_steps().tolist() == [round(steps / 2), steps]
    picked = mean[[round(steps / 2) - 1, steps - 1]].transpose(0, 1).flatten(1)  # [N, 6]
    nodes_ref = (picked - picked.mean(0)) / picked.std(0, correction=0)
    flat = mean.reshape(-1, 3)
    point_ref = (mean.transpose(0, 1) - flat.mean(0)) / flat.std(0, correction=0)  # [N, T, 3]
    seen = {}
    model.model.register_forward_pre_hook(lambda m, args: seen.update(nodes=args[0]["l0"][:, -6:]))
    model.decoder.lin_point.register_forward_pre_hook(lambda m, args: seen.update(point=args[0]))
    traj = TrajectoryDataset(tiny_data, "test")[0]
    h = _hierarchy(traj)
    (alone,) = predict_direct(model.eval(), [traj], h)
    torch.testing.assert_close(seen["nodes"].double(), nodes_ref, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(seen["point"].double(), point_ref, atol=1e-4, rtol=1e-4)
    without, _ = _fitted(tiny_data)
    assert (alone - predict_direct(without.eval(), [traj], h)[0]).abs().max() > 1e-3  # it is read
    trajs = [traj, *train.trajectories]
    for a, b in zip(
        [predict_direct(model, [t], h)[0] for t in trajs],
        predict_direct(model, trajs, h, batch_size=2),
        strict=True,
    ):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    loaded = DirectSurrogate.load(model.save(tmp_path / "direct.pt", {}))
    torch.testing.assert_close(predict_direct(loaded, [traj], h)[0], alone)
    with pytest.raises(ValueError, match="base_input must be 0, or >= 1 with base='mean'"):
        DirectSurrogate(base="initial", base_input=2)


def _lifted_prior(traj, lift: float = 0.3):
    """A prior of ``traj``: its positions, the plies moved by ``lift * t * (1, -0.5, 2)`` mm at step ``t``."""
    prior = traj.pos.clone()
    steps = torch.arange(prior.size(0), dtype=prior.dtype)[:, None, None]  # [T+1, 1, 1]
    prior[:, traj.ply_mask] += lift * steps * torch.tensor([1.0, -0.5, 2.0], dtype=prior.dtype)
    return prior


def test_the_prior_base_departs_from_each_samples_prior(tiny_data):
    """``base="prior"``: the target scale is the departure's spread; a zero output is the prior."""
    train_trajs = list(TrajectoryDataset(tiny_data, "train"))
    stems = [f.stem for f in TrajectoryDataset(tiny_data, "train").files]
    lifts = [0.3 * (i + 1) for i in range(len(stems))]
    priors = {s: _lifted_prior(t, a) for s, t, a in zip(stems, train_trajs, lifts, strict=True)}
    torch.manual_seed(0)
    model = DirectSurrogate(**SMALL, base="prior")
    assert model.prior_features  # so that the data module, test and design supply the prior
    train = DirectDataset(tiny_data, "train", max_levels=2, transform=model.contact, priors=priors)
    for i in range(len(train)):
        model.accumulate_statistics(train[i])
    model.freeze_statistics()
    departures = [  # float64 reference: truth minus prior on ply nodes, every step
        (t.pos[1:].double() - priors[s][1:].double())[:, t.ply_mask].reshape(-1, 3)
        for s, t in zip(stems, train_trajs, strict=True)
    ]
    spread = torch.cat(departures).std(0, correction=0)  # [3]
    torch.testing.assert_close(model.target_norm.std.double(), spread, rtol=1e-5, atol=1e-9)

    last = model.decoder.rest[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    traj = TrajectoryDataset(tiny_data, "test")[0]
    prior = _lifted_prior(traj, 0.7)
    (pred,) = predict_direct(model.eval(), [dataclasses.replace(traj, prior=prior)], _hierarchy(traj))
    ply = traj.ply_mask
    torch.testing.assert_close(pred[1:, ply], prior[1:, ply].float(), atol=1e-5, rtol=0)
    torch.testing.assert_close(pred[:, ~ply], traj.pos[:, ~ply].float())
    with pytest.raises(ValueError, match="no prior trajectory"):
        predict_direct(model, [traj], _hierarchy(traj))


def test_one_line_errors():
    with pytest.raises(ValueError, match="base must be one of"):
        DirectSurrogate(base="median")
    with pytest.raises(ValueError, match="time_frequencies must be >= 1"):
        TimeEncoding(0)
    from torch_ampn.training import DirectLightningModule, NextStepLightningModule

    with pytest.raises(
        TypeError, match=r"^DirectLightningModule: diffusion_steps is NextStepLightningModule's"
    ):
        DirectLightningModule(diffusion_steps=5)
    with pytest.raises(TypeError, match=r"^NextStepLightningModule: base is DirectLightningModule's"):
        NextStepLightningModule(base="prior")
    with pytest.raises(TypeError, match=r"^DirectLightningModule: no argument hiden_channels"):
        DirectLightningModule(hiden_channels=5)


def test_the_time_encoding_is_a_hand_computed_case():
    code = TimeEncoding(2)(torch.tensor([0.25]))
    pi = torch.pi
    expected = torch.tensor(
        [[0.25, torch.sin(torch.tensor(pi / 4)), 1.0, torch.cos(torch.tensor(pi / 4)), 0.0]]
    )
    torch.testing.assert_close(code, expected, atol=1e-6, rtol=0)


def test_direct_arguments_of_the_module_match_the_direct_surrogate():
    import inspect

    from torch_ampn.nn import RobinAMPN
    from torch_ampn.training import DirectLightningModule
    from torch_ampn.training.checkpoint import module_defaults
    from torch_ampn.training.direct_module import DIRECT_ARGUMENTS

    module = module_defaults(DirectLightningModule)
    owners = {**inspect.signature(RobinAMPN).parameters, **inspect.signature(DirectSurrogate).parameters}
    for name in DIRECT_ARGUMENTS:
        assert name in module and name in owners, name
        if name not in ("contact_radius",):  # the module's default is the paper's, as the surrogate's
            assert module[name] == owners[name].default, name


def without_next_step(model: dict) -> dict:
    """The tiny fit's model settings without the next-step module's own (``fast_rollout``)."""
    return {k: v for k, v in model.items() if k != "fast_rollout"}


@pytest.mark.xdist_group("tiny_fit")
def test_cli_fit_with_weight_averaging_test_predict_and_export_of_a_direct_model(tiny_data, tmp_path, capsys):
    """The CLI path end to end; the averaged checkpoint keeps the mean base of the training runs."""
    import csv
    import json

    import yaml
    from make_fixtures import fit_config

    from torch_ampn.cli.export import main as export
    from torch_ampn.cli.train import main
    from torch_ampn.training import DirectLightningModule

    config_path, out = fit_config(tmp_path / "fit", tiny_data)
    config = yaml.safe_load(config_path.read_text())
    config["model"] = {"class_path": "torch_ampn.training.DirectLightningModule",
                       "init_args": {**without_next_step(config["model"]), "loss_steps": 3}}  # fmt: skip
    config["trainer"]["max_steps"] = 4
    config["trainer"]["val_check_interval"] = 2
    config["trainer"]["callbacks"].append(
        {"class_path": "lightning.pytorch.callbacks.EMAWeightAveraging", "init_args": {"decay": 0.9}}
    )
    config_path.write_text(yaml.safe_dump(config))
    main(["fit", "--config", str(config_path)])
    ckpt = out / "ckpt" / "last.ckpt"
    module = DirectLightningModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    surrogate = module.surrogate
    assert isinstance(surrogate, DirectSurrogate) and surrogate.statistics_frozen
    train = TrajectoryDataset(tiny_data, "train")
    mean = torch.stack([t.pos[1:].double() - t.pos[0].double() for t in train]).mean(0)  # [T, N, 3]
    saved = surrogate.base_norm.running_mean.reshape(mean.shape)
    torch.testing.assert_close(saved, mean, atol=1e-6, rtol=1e-6)

    capsys.readouterr()
    common = ["--data.data_dir", str(tiny_data), "--data.generate", "false", "--data.min_coarse_nodes", "4"]
    main(["test", "--ckpt_path", str(ckpt), *common, "--model.output_dir", str(out / "reports")])
    printed = capsys.readouterr().out
    assert "best setting-aware baseline" in printed
    with open(out / "reports" / "test_rmse.csv") as f:
        rows = list(csv.DictReader(f))
    traj = TrajectoryDataset(tiny_data, "test")[0]
    (pred,) = predict_direct(surrogate, [traj], _hierarchy(traj))
    from torch_ampn.rollout import rollout_rmse

    by_hand = float(rollout_rmse(pred, traj.pos, traj.ply_mask)[1:].mean())
    assert float(rows[0]["model"]) == pytest.approx(by_hand, rel=1e-4)
    summary = json.loads((out / "reports" / "test_summary.json").read_text())
    assert {"setting_baseline_rmse", "mean_trajectory_rmse", "setting_effect_r2"} <= set(summary)

    settings = tmp_path / "settings.yaml"
    settings.write_text(
        yaml.safe_dump([{"name": "wide", "gripper_positions": [0.2, 0.8], "gripper_forces": [90.0, 10.0]}])
    )
    main(
        [
            "predict",
            "--ckpt_path",
            str(ckpt),
            *common,
            "--data.predict_file",
            str(settings),
            "--model.output_dir",
            str(out / "reports"),
        ]
    )
    assert (out / "reports" / "predict" / "wide.json").is_file()

    from torch_ampn.cli.design import main as design
    from torch_ampn.design import SettingsSpace, part_quality, settings_trajectories

    budget = ["--maxiter", "1", "--popsize", "2", "--map-points", "3", "--top", "2", "--batch-size", "3"]
    report = design([str(tiny_data), "--checkpoint", str(ckpt), "--measure", "draw_in_mean",
                     "--out", str(tmp_path / "design"), *budget])  # fmt: skip
    best = report["best"]  # searched on the formed part alone; judged here on the whole prediction
    from torch_ampn.training import AMPNDataModule

    cfg = AMPNDataModule(str(tiny_data), generate=False).simulator_config()
    x = np.array([list(best["settings"].values())])  # [1, D]
    (best_traj,) = settings_trajectories(cfg, SettingsSpace.from_config(cfg), x)
    (whole,) = predict_direct(surrogate, [best_traj], _hierarchy(best_traj))
    by_hand = part_quality(best_traj, whole[-1], names={"draw_in_mean": 1.0})["draw_in_mean"]
    assert best["objective"] == pytest.approx(by_hand, rel=1e-4, abs=1e-6)
    assert report["search"]["evaluations"] == 2 * 2 * 4 and (tmp_path / "design" / "top_1.xdmf").is_file()

    path = export([str(ckpt), str(tmp_path / "direct.pt")])
    loaded = DirectSurrogate.load(path)
    torch.testing.assert_close(predict_direct(loaded, [traj], _hierarchy(traj))[0], pred)


@pytest.mark.xdist_group("tiny_fit")
def test_cli_fit_test_and_design_of_a_direct_model_on_a_prior(tiny_data, tmp_path, capsys):
    """``base: prior``, ``data.prior``: out-of-fold priors in training, the fitted one in test and design."""
    import json

    import yaml
    from make_fixtures import fit_config

    from torch_ampn.baselines.prior import fitted_prior
    from torch_ampn.cli.design import main as design
    from torch_ampn.cli.train import main
    from torch_ampn.training import DirectLightningModule

    config_path, out = fit_config(tmp_path / "fit", tiny_data)
    config = yaml.safe_load(config_path.read_text())
    config["model"] = {"class_path": "torch_ampn.training.DirectLightningModule",
                       "init_args": {**without_next_step(config["model"]), "loss_steps": 3,
                                     "base": "prior"}}  # fmt: skip
    config["data"].update(prior="mean_trajectory", prior_folds=2)
    config["trainer"].update(max_steps=2, val_check_interval=2)
    config_path.write_text(yaml.safe_dump(config))
    main(["fit", "--config", str(config_path)])
    ckpt = out / "ckpt" / "last.ckpt"
    surrogate = DirectLightningModule.load_from_checkpoint(ckpt, map_location="cpu").eval().surrogate
    assert isinstance(surrogate, DirectSurrogate) and surrogate.base == "prior"

    common = ["--data.data_dir", str(tiny_data), "--data.generate", "false", "--data.min_coarse_nodes", "4"]
    common += ["--data.prior", "mean_trajectory", "--data.prior_folds", "2"]  # as in the fit
    main(["test", "--ckpt_path", str(ckpt), *common, "--model.output_dir", str(out / "reports")])
    summary = json.loads((out / "reports" / "test_summary.json").read_text())
    traj = TrajectoryDataset(tiny_data, "test")[0]
    prior = fitted_prior("mean_trajectory", list(TrajectoryDataset(tiny_data, "train")))  # the whole split
    with_prior = dataclasses.replace(traj, prior=prior.predict(traj))
    (pred,) = predict_direct(surrogate, [with_prior], _hierarchy(traj))
    from torch_ampn.rollout import rollout_rmse

    by_hand = float(rollout_rmse(pred, traj.pos, traj.ply_mask)[1:].mean())
    assert summary["rollout_rmse"] == pytest.approx(by_hand, rel=1e-4)

    budget = ["--maxiter", "1", "--popsize", "2", "--map-points", "3", "--top", "1"]
    report = design([str(tiny_data), "--checkpoint", str(ckpt), "--measure", "draw_in_mean",
                     "--out", str(tmp_path / "design"), *budget])  # fmt: skip
    assert report["search"]["evaluations"] == 2 * 2 * 4
