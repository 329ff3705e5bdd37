"""Why a next-step model errs: the single step, the rollout, and what the settings reach, per saved step.

    python benchmarks/next_step_diagnosis.py benchmarks/results/next_step_v3/ampn_seed0.ckpt \\
        benchmarks/results/next_step_v3/flat_seed0.ckpt --data-dir data/v3_192 \\
        --out benchmarks/results/next_step_v3/diagnosis.json

For each checkpoint (a next-step model, e.g. a cell of ``benchmarks/compare.py``), on every test
trajectory of ``--data-dir``, per saved step ``t``:

- ``rollout``: the RMSE of the model's rollout from the initial state (the paper's metric);
- ``one_step``: teacher forced, the step ``t`` predicted from the *true* states ``t-1, t-2``
  (:func:`~torch_ampn.rollout.one_step_predictions`): the single step's error, none carried over;
- ``restart``: the rollout from the true state at ``--restart`` (default: half way): how much of
  the late error is the late steps' own, and how much the early steps' carried over;
- beside them the setting-aware baselines fitted on the training split (the mean trajectory, the
  nearest setting, a linear regression on the settings, POD + GP) and, for the single step, the
  constant-velocity step (step ``t`` repeats step ``t - 1``) and the mean trajectory's and POD +
  GP's steps, each taken from the true state ``t - 1`` (``*_one_step``);
- the R² of the setting effect per step, ``1 - MSE_t / MSE_t(mean trajectory)`` over the test
  trajectories (1: every setting's effect predicted; 0: no better than ignoring the settings).

Prints a table at a few steps, writes the JSON atomically and a figure beside it.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torch_ampn.baselines import fit_setting_baselines
from torch_ampn.rollout import one_step_predictions, rollout_plain, rollout_rmse
from torch_ampn.utils.io import atomic_write_text

from device_info import device_name  # benchmarks/device_info.py, beside this script

#: Steps the printed table shows (those past the last saved step are dropped).
SHOWN_STEPS = (1, 5, 10, 20, 25, 26, 30, 40, 50)


def _squared(pred: torch.Tensor, true: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """Squared RMSE per step ``[T+1]`` (mm^2)."""
    return rollout_rmse(pred, true, mask).double().square().numpy()


def constant_velocity(true: torch.Tensor) -> torch.Tensor:
    """Teacher-forced constant velocity ``[T+1, N, 3]``: ``x_t = 2 x_{t-1} - x_{t-2}`` (``x_{-1} = x_0``)."""
    prev = torch.cat([true[:1], true[:-1]])  # [T+1, N, 3]: x_{t-1}
    prev_prev = torch.cat([true[:1], true[:1], true[:-2]])  # x_{t-2}
    return (2 * prev - prev_prev).float()


def zero_noise_predictor(surrogate: Any) -> Any:
    """The surrogate with its noise input at the noise's mean (zeros) instead of N(0, 1) draws.

    AMPN (K = 1) reads pure N(0, 1) noise beside its features (ROBIN's noisy target with
    :math:`\\bar\\alpha_1 = 0`); its target does not depend on it, so a network that learnt to ignore
    it predicts the same with zeros, and one that did not is a random predictor.
    """

    def predict(data: Any) -> torch.Tensor:
        x_dict, index_dict, attr_dict = surrogate.normalized_features(data)
        shape = (data["l0"].num_nodes, surrogate.model.noise_channels)
        return surrogate.residual_from_features(
            x_dict, index_dict, attr_dict, data["l0"].prev_disp, draw=lambda: torch.zeros(shape)
        )

    return predict


def teacher_forced_steps(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """A whole-trajectory prediction's steps from the true states: ``true_{t-1} + pred_t - pred_{t-1}``.

    ``[T+1, N, 3]``: the one-step error of a predictor of whole trajectories (e.g. POD + GP), for
    comparison with a next-step model's :func:`~torch_ampn.rollout.one_step_predictions`.
    """
    out = true.clone().float()
    out[1:] = true[:-1].float() + (pred[1:] - pred[:-1]).float()
    return out


def diagnose(module: Any, items: list, restart: int, progress: bool = False) -> dict[str, np.ndarray]:
    """Per-step squared errors ``[K, T+1]`` of the model's rollout, one step and restart over ``items``.

    For K = 1 also with the noise input at zero (:func:`zero_noise_predictor`), and the distance
    between two rollouts of other noise draws (``noise_spread``: how random the predictor is).
    """
    surrogate = module.surrogate.eval()
    bundle = surrogate.bundle_steps  # steps per call (temporal bundling)
    out: dict[str, list[np.ndarray]] = {"rollout": [], "one_step": [], "restart": []}
    if surrogate.diffusion_steps == 1:
        out |= {"rollout_zero_noise": [], "one_step_zero_noise": [], "noise_spread": []}
    iterator = items
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(items, desc="test trajectories", unit="traj")
    for item in iterator:
        traj, hierarchy = item.trajectory, item.hierarchy
        generator = torch.Generator().manual_seed(item.index)
        predict = functools.partial(surrogate.predict_residual, generator=generator)
        ply = traj.ply_mask
        rolled = rollout_plain(predict, traj, hierarchy, surrogate.contact, bundle_steps=bundle)
        one = one_step_predictions(predict, traj, hierarchy, surrogate.contact, bundle_steps=bundle)
        late = rollout_plain(predict, traj, hierarchy, surrogate.contact, start=restart, bundle_steps=bundle)
        out["rollout"].append(_squared(rolled, traj.pos, ply))
        out["one_step"].append(_squared(one, traj.pos, ply))
        out["restart"].append(_squared(late, traj.pos, ply))
        if surrogate.diffusion_steps == 1:
            zero = zero_noise_predictor(surrogate)
            out["rollout_zero_noise"].append(
                _squared(
                    rollout_plain(zero, traj, hierarchy, surrogate.contact, bundle_steps=bundle),
                    traj.pos,
                    ply,
                )
            )
            out["one_step_zero_noise"].append(
                _squared(
                    one_step_predictions(zero, traj, hierarchy, surrogate.contact, bundle_steps=bundle),
                    traj.pos,
                    ply,
                )
            )
            other = functools.partial(
                surrogate.predict_residual, generator=torch.Generator().manual_seed(10**6 + item.index)
            )
            out["noise_spread"].append(
                _squared(
                    rollout_plain(other, traj, hierarchy, surrogate.contact, bundle_steps=bundle), rolled, ply
                )
            )
    return {k: np.stack(v) for k, v in out.items()}


def baselines(train: list, test: list) -> dict[str, np.ndarray]:
    """Per-step squared errors ``[K, T+1]`` of the setting-aware baselines and the constant-velocity step."""
    fitted, reason = fit_setting_baselines(train)
    if reason is not None:
        raise SystemExit(f"next_step_diagnosis.py: no setting baselines: {reason}")
    out = {
        name: np.stack([_squared(b.predict(t), t.pos, t.ply_mask) for t in test])
        for name, b in fitted.items()
    }
    for name in ("mean_trajectory", "pod_gp"):
        steps = [teacher_forced_steps(fitted[name].predict(t), t.pos) for t in test]
        out[f"{name}_one_step"] = np.stack(
            [_squared(p, t.pos, t.ply_mask) for p, t in zip(steps, test, strict=True)]
        )
    out["constant_velocity_one_step"] = np.stack(
        [_squared(constant_velocity(t.pos), t.pos, t.ply_mask) for t in test]
    )
    return out


def summarise(squared: dict[str, np.ndarray], mean_trajectory: np.ndarray, restart: int) -> dict[str, Any]:
    """Per-step RMSE (root of the mean over trajectories of the squared RMSE) and R²; their means."""
    reference = mean_trajectory.mean(0)  # [T+1]
    out: dict[str, Any] = {}
    for name, sq in squared.items():
        per_step = sq.mean(0)  # [T+1]
        steps = slice(restart + 1, None) if name == "restart" else slice(1, None)
        r2 = np.full_like(per_step, np.nan)
        r2[1:] = 1.0 - per_step[1:] / reference[1:]
        out[name] = {
            "rmse_per_step": np.sqrt(per_step).tolist(),
            "r2_per_step": r2.tolist(),
            "rmse": float(np.sqrt(sq[:, steps]).mean()),  # the paper's mean over trajectories and steps
            "rmse_after_restart": float(np.sqrt(sq[:, restart + 1 :]).mean()),
            "r2": float(1.0 - per_step[steps].mean() / reference[steps].mean()),
        }
    return out


def print_table(results: dict[str, Any], restart: int) -> None:
    """Per model: the RMSE [mm] and the R² of the setting effect of every predictor at a few steps."""
    for label, rows in results.items():
        num_steps = len(next(iter(rows.values()))["rmse_per_step"]) - 1
        shown = [t for t in SHOWN_STEPS if t <= num_steps]
        for key, title, fmt in (("rmse_per_step", "RMSE [mm]", "{:7.3f}"), ("r2_per_step", "R²", "{:+7.2f}")):
            print(f"\n{label}: {title} at saved step t (restart from the true state at t = {restart})")
            print(f"| {'predictor':28s} |" + "".join(f" t = {t:2d} |" for t in shown) + " mean RMSE |")
            print("|---|" + "---:|" * (len(shown) + 1))
            for name, r in rows.items():
                cells = [
                    "      -" if name == "restart" and t <= restart else fmt.format(r[key][t]) for t in shown
                ]
                print(f"| {name:28s} |" + "".join(f" {c} |" for c in cells) + f" {r['rmse']:9.3f} |")


def plot(path: Path, results: dict[str, Any], restart: int) -> None:
    """RMSE per step of each model's rollout, one step and restart, with the baselines (log scale)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6.5 * len(results), 4.5), squeeze=False)
    styles = {
        "rollout": "-",
        "one_step": "--",
        "restart": ":",
        "rollout_zero_noise": "-.",
        "noise_spread": (0, (1, 3)),
    }
    for ax, (label, rows) in zip(axes[0], results.items(), strict=True):
        for name, r in rows.items():
            y = np.asarray(r["rmse_per_step"])
            t = np.arange(len(y))
            keep = t > (restart if name == "restart" else 0)
            if name in styles:
                ax.semilogy(
                    t[keep], y[keep], linestyle=styles[name], lw=2, label=f"model: {name.replace('_', ' ')}"
                )
            else:
                ax.semilogy(t[keep], y[keep], lw=1, alpha=0.7, label=name.replace("_", " "))
        ax.axvline(restart, color="grey", lw=0.5)
        ax.set(xlabel="saved step t", ylabel="RMSE [mm]", title=label)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", type=Path, help="next-step checkpoints (.ckpt)")
    parser.add_argument("--data-dir", type=Path, required=True, help="dataset with train and test splits")
    parser.add_argument("--labels", nargs="*", help="one per checkpoint (default: the file stems)")
    parser.add_argument("--restart", type=int, default=None, help="restart step (default: half way)")
    parser.add_argument("--limit", type=int, default=None, help="first N test trajectories only")
    parser.add_argument("--out", type=Path, required=True, help="JSON (the figure: same name, .png)")
    args = parser.parse_args(argv)
    from torch_ampn.data import TrajectoryDataset
    from torch_ampn.training import load_module
    from torch_ampn.training.datamodule import AMPNDataModule

    labels = args.labels or [p.stem for p in args.checkpoints]
    if len(labels) != len(args.checkpoints):
        parser.error(f"--labels: {len(labels)} labels for {len(args.checkpoints)} checkpoints")
    train = list(TrajectoryDataset(args.data_dir, "train", max_cached_mb=0))
    results: dict[str, Any] = {}
    reference: dict[str, np.ndarray] | None = None
    for label, ckpt in zip(labels, args.checkpoints, strict=True):
        module = load_module(ckpt, map_location="cpu").eval()
        hp = module.hparams
        if hp.get("prior_features"):
            raise SystemExit(f"next_step_diagnosis.py: {ckpt}: a model on a prior is not diagnosed here")
        dm = AMPNDataModule(str(args.data_dir), generate=False, max_levels=hp.num_levels)
        split = dm._rollout_split("test", limit=args.limit)
        items = [split[i] for i in range(len(split))]
        num_steps = items[0].trajectory.num_steps
        restart = num_steps // 2 if args.restart is None else args.restart
        if reference is None:
            reference = baselines(train, [it.trajectory for it in items])
        with torch.inference_mode():
            squared = diagnose(module, items, restart, progress=True)
        results[label] = summarise({**squared, **reference}, reference["mean_trajectory"], restart)
    print_table(results, restart)
    report = {
        "date": datetime.date.today().isoformat(),
        "machine": device_name("cpu"),
        "data_dir": str(args.data_dir),
        "train_trajectories": len(train),
        "test_trajectories": len(items),
        "restart": restart,
        "checkpoints": {label: str(p) for label, p in zip(labels, args.checkpoints, strict=True)},
        "results": results,
    }
    atomic_write_text(args.out, json.dumps(report, indent=1))
    plot(args.out.with_suffix(".png"), results, restart)
    print(f"\nwrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
