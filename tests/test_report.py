"""End-of-run lines: the test verdict (one per baseline not beaten) and a fit that ended short."""

from torch_ampn.training.report import verdict


def _summary(model, trivial, aware=None):
    out = {"rollout_rmse": model, "baseline_rmse": trivial}
    if aware is not None:
        out.update(setting_baseline="pod_gp", setting_baseline_rmse=aware)
    return out


def test_verdict_says_plainly_when_the_model_beats_every_baseline():
    (line,) = verdict(_summary(0.2, 3.0, 0.3))
    assert line.startswith("RESULT: the model (0.2000 mm) beats") and "pod_gp (0.3000 mm)" in line
    assert "0.67 times its error" in line  # 0.2 / 0.3
    assert verdict(_summary(0.2, 3.0)) == []  # no setting-aware baseline: nothing more to say


def test_verdict_names_each_baseline_the_model_does_not_beat():
    (line,) = verdict(_summary(0.62, 3.05, 0.31))
    assert line.startswith("WARNING:") and "pod_gp (0.3100 mm)" in line and "0.6200 mm" in line
    lines = verdict(_summary(6.34, 3.97, 0.5))
    assert len(lines) == 2 and "trivial baseline (3.9700 mm)" in lines[0]
    # a tie is not a win
    assert len(verdict(_summary(0.5, 0.5))) == 1
    (line,) = verdict(_summary(0.3, 3.0, 0.3))
    assert line.startswith("WARNING:")


def test_shortfall_line_only_when_a_fit_ends_before_its_planned_steps():
    from torch_ampn.cli.train import shortfall

    assert shortfall(3000, 3000) is None
    assert shortfall(10, -1) is None  # no step limit planned
    line = shortfall(930, 3000)
    assert line.startswith("WARNING:") and "930 of its planned 3000 steps (31 %)" in line


def test_fit_progress_prints_the_whole_fits_rate_and_eta(monkeypatch, capsys):
    from types import SimpleNamespace

    import torch_ampn.training.progress as progress

    clock = iter([0.0, 600.0, 700.0, 800.0])  # start; step 1 (compiles 600 s); steps 250, 500
    monkeypatch.setattr(progress.time, "perf_counter", lambda: next(clock))
    trainer = SimpleNamespace(global_step=0, max_steps=1000, is_global_zero=True)
    module = SimpleNamespace(hparams={"compile_network": True})
    callback = progress.FitProgress(every_n_steps=250)
    callback.on_train_start(trainer, module)
    for step in (1, 250, 500):
        trainer.global_step = step
        callback.on_train_batch_end(trainer, module, None, None, step - 1)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "[fit] the first step took 10 min 00 s (compiling the training step)"
    # 249 steps in 100 s: 2.49 steps/s, 750 steps left -> 301 s
    assert lines[1] == "[fit] step 250/1000, 2.49 steps/s, 11 min 40 s so far, ETA 5 min 01 s"
    assert lines[2] == "[fit] step 500/1000, 2.50 steps/s, 13 min 20 s so far, ETA 3 min 20 s"


def test_format_seconds():
    from torch_ampn.training.progress import format_seconds

    assert [format_seconds(s) for s in (0.4, 59, 60, 3599, 3720)] == [
        "0 s", "59 s", "1 min 00 s", "59 min 59 s", "1 h 02 min",
    ]  # fmt: skip


def test_cli_after_fit_warns_and_with_the_main_jobs_setting_exits_3(monkeypatch, capsys):
    from types import SimpleNamespace

    import pytest

    from torch_ampn.cli.train import AMPNCLI

    cli = AMPNCLI.__new__(AMPNCLI)  # only the hook: no parser, no Trainer
    cli.trainer = SimpleNamespace(global_step=3000, max_steps=3000)
    monkeypatch.setenv("AMPN_REQUIRE_PLANNED_STEPS", "1")
    cli.after_fit()
    assert capsys.readouterr().err == ""
    cli.trainer.global_step = 75
    with pytest.raises(SystemExit) as exit_:
        cli.after_fit()
    assert exit_.value.code == 3 and "75 of its planned 3000 steps" in capsys.readouterr().err
    monkeypatch.delenv("AMPN_REQUIRE_PLANNED_STEPS")
    cli.after_fit()  # a user's own fit: the line only
    assert "WARNING" in capsys.readouterr().err


def test_the_error_picture_draws_the_baselines_that_use_the_training_data(tmp_path):
    """The model is drawn beside the trivial and the setting-aware baselines, each line their mean curve."""
    import matplotlib

    matplotlib.use("Agg")
    import torch

    from torch_ampn.training.report import TestReport

    report = TestReport(tmp_path)
    curves = {
        "model": [torch.tensor([0.0, 1.0, 2.0]), torch.tensor([0.0, 3.0, 4.0])],
        "static": [torch.tensor([0.0, 5.0, 9.0])] * 2,
        "pod_gp": [torch.tensor([0.0, 0.5, 1.0]), torch.tensor([0.0, 1.5, 2.0])],
        "mean_trajectory": [torch.tensor([0.0, 4.0, 6.0])] * 2,
    }
    report.curves = curves
    fig = report.over_time_figure({})
    (ax,) = fig.axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["model", "static", "mean_trajectory", "pod_gp"]
    lines = {line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")}
    # from step 1 (step 0 is the given initial state): the mean over the trajectories
    assert lines["pod_gp"].get_ydata().tolist() == [1.0, 1.5] and lines["pod_gp"].get_linestyle() == "--"
    assert lines["model"].get_ydata().tolist() == [2.0, 3.0] and lines["model"].get_xdata().tolist() == [1, 2]
