"""Files written by ``torch-ampn test`` and ``predict``: RMSE table, plots, XDMF rollouts."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torch_ampn.baselines.settings import SETTING_BASELINE_NAMES
from torch_ampn.data.trajectory import Trajectory
from torch_ampn.training.items import RolloutItem
from torch_ampn.utils.io import atomic_savefig, atomic_write_text


def _figure():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def verdict(summary: dict[str, float | str]) -> list[str]:
    """The end of a test in plain words: one ``WARNING`` line for each baseline the model does not beat.

    Checked: the best trivial baseline (``baseline_rmse``) and, where reported, the best
    setting-aware one (``setting_baseline_rmse``, e.g. POD + GP). When the model beats the
    setting-aware baseline, one ``RESULT`` line says so, with the ratio of the errors; when it
    beats the trivial one and no setting-aware baseline is reported, the list is empty.
    """
    model = float(summary["rollout_rmse"])
    lines = []
    if model >= float(summary["baseline_rmse"]):
        lines.append(
            f"WARNING: the model ({model:.4f} mm) tests no better than the best trivial baseline "
            f"({float(summary['baseline_rmse']):.4f} mm), which ignores the training data"
        )
    if "setting_baseline_rmse" in summary:
        aware, name = float(summary["setting_baseline_rmse"]), summary["setting_baseline"]
        if model >= aware:
            lines.append(
                f"WARNING: the model ({model:.4f} mm) tests no better than the setting-aware baseline "
                f"{name} ({aware:.4f} mm), built from the same training trajectories"
            )
        else:
            lines.append(
                f"RESULT: the model ({model:.4f} mm) beats the best setting-aware baseline {name} "
                f"({aware:.4f} mm), built from the same training trajectories: "
                f"{model / aware:.2f} times its error"
            )
    return lines


def plot_final_shapes(path: Path, traj: Trajectory, pred: Tensor, title: str) -> None:
    """Predicted vs true final shape of the bottom ply (seen from below), coloured by e3 displacement."""
    from torch_ampn.viz import plot_laminate

    plt = _figure()
    ply = traj.ply_mask
    u3_true = traj.pos[-1, :, 2] - traj.pos[0, :, 2]
    u3_pred = pred[-1, :, 2] - traj.pos[0, :, 2]
    vmin = float(torch.minimum(u3_true[ply].min(), u3_pred[ply].min()))
    fig = plt.figure(figsize=(13, 5.5))
    last = None
    for j, (label, pos, u3) in enumerate((("predicted", pred[-1], u3_pred), ("true", traj.pos[-1], u3_true))):
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        last = plot_laminate(
            ax, pos, traj.cells, traj.node_type, u3, vmin, 0.0, show_tools=False, components=[0]
        )
        ax.view_init(elev=28, azim=-62)
        ax.set_title(f"{label}: final step {traj.num_steps}, bottom ply")
    fig.colorbar(last, ax=fig.axes, shrink=0.6, label="e3 displacement [mm]")
    fig.suptitle(title)
    atomic_savefig(fig, path)
    plt.close(fig)


def part_label(part: dict | None) -> str:
    """Short label of a family trajectory's part (``meta["part"]``): ``double dome, 4 plies, 47 mm``."""
    if not part:
        return ""
    shape = str(part.get("shape", "part")).replace("_", " ")
    return f"{shape}, {len(part.get('ply_angles', ()))} plies, {float(part.get('dome_depth', 0.0)):.0f} mm"


#: The setting-aware baselines' columns (:func:`torch_ampn.baselines.setting_baselines`).
SETTING_BASELINES = SETTING_BASELINE_NAMES


class TestReport:
    """Collects per-trajectory rollout errors and writes the test outputs into ``folder``.

    Files: ``test_rmse.csv`` (one row per trajectory: model and baseline RMSE in mm,
    averaged over steps, and the rollout time), ``test_summary.json``,
    ``rmse_over_time.csv`` (one row per step: the model's and every baseline's RMSE, mean
    over trajectories), ``rmse_over_time.png``, ``final_shape_<name>.png`` (first trajectory) and, with
    ``xdmf``, ``xdmf/<name>.xdmf`` (true and predicted displacement, error field).
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.rows: list[dict] = []
        self.curves: dict[str, list[Tensor]] = {}

    def add(
        self,
        item: RolloutItem,
        pred: Tensor,
        rmse: Tensor,
        baselines: dict[str, Tensor],
        seconds: float,
        xdmf: bool = True,
    ) -> None:
        """Record one test trajectory (and write its XDMF file, and the shape figure for the first)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        row = {"trajectory": item.name}
        label = part_label(item.trajectory.meta.get("part"))
        if label:
            row["part"] = label
        row["model"] = float(rmse[1:].mean())
        row.update({name: float(curve[1:].mean()) for name, curve in baselines.items()})
        row["rollout_seconds"] = seconds
        self.rows.append(row)
        for name, curve in {"model": rmse, **baselines}.items():
            self.curves.setdefault(name, []).append(curve)
        if xdmf:
            from torch_ampn.data.meshio_io import export_xdmf

            export_xdmf(item.trajectory, self.folder / "xdmf" / f"{item.name}.xdmf", predicted_pos=pred)
        if item.index == 0:
            plot_final_shapes(
                self.folder / f"final_shape_{item.name}.png",
                item.trajectory,
                pred,
                f"{item.name}: rollout RMSE {row['model']:.3f} mm (averaged over steps)",
            )

    def merge(self, parts: list[tuple[list[dict], dict[str, list[Tensor]]]]) -> None:
        """Take the ``(rows, curves)`` of every rank (this one's included): each trajectory once, by name."""
        found: dict[str, tuple[dict, dict[str, Tensor]]] = {}
        for rows, curves in parts:
            for i, row in enumerate(rows):
                found.setdefault(row["trajectory"], (row, {name: c[i] for name, c in curves.items()}))
        names = sorted(found)
        self.rows = [found[n][0] for n in names]
        kinds = list(found[names[0]][1]) if names else []
        self.curves = {kind: [found[n][1][kind] for n in names] for kind in kinds}

    def mse(self, name: str) -> float:
        """Mean over trajectories and steps ``1 .. T`` of ``name``'s squared per-step RMSE (mm^2)."""
        curves = self.curves[name]
        return float(sum(c[1:].double().square().mean() for c in curves) / len(curves))

    def summary(self) -> dict[str, float | str]:
        """Means over trajectories: model, static, best rigid and best trivial baseline RMSE, the ratio.

        With setting-aware baselines (:data:`SETTING_BASELINES`), the best of them and the
        explained variance of the setting effect (``setting_effect_r2``: model against the mean
        training trajectory, :func:`~torch_ampn.baselines.setting_effect_r2`).
        """
        mean = {k: sum(r[k] for r in self.rows) / len(self.rows) for k in self._numeric()}
        rigid = {k: v for k, v in mean.items() if k.startswith("rigid")}
        best_rigid = min(rigid, key=rigid.get) if rigid else None
        baseline = min(mean["static"], rigid[best_rigid] if best_rigid else float("inf"))
        out: dict[str, float | str] = {
            "rollout_rmse": mean["model"],
            "static_rmse": mean["static"],
            "baseline_rmse": baseline,
            "improvement_over_baseline": baseline / max(mean["model"], 1e-12),
            "rollout_seconds": mean["rollout_seconds"],
        }
        if best_rigid:
            out["rigid_rmse"] = rigid[best_rigid]
            out["rigid_touch_radius"] = float(best_rigid.removeprefix("rigid_r"))
        # a baseline that could not place some trajectory (NaN there) is left out of the comparison
        aware = {k: mean[k] for k in SETTING_BASELINES if k in mean and math.isfinite(mean[k])}
        if "mean_trajectory" in aware:
            from torch_ampn.baselines import setting_effect_r2

            best = min(aware, key=aware.get)
            reference = self.mse("mean_trajectory")
            out.update(
                mean_trajectory_rmse=aware["mean_trajectory"],
                setting_baseline=best,
                setting_baseline_rmse=aware[best],
                model_over_setting_baseline=mean["model"] / max(aware[best], 1e-12),
                setting_effect_r2=setting_effect_r2(self.mse("model"), reference),
                **{f"{k}_r2": setting_effect_r2(self.mse(k), reference) for k in aware},
            )
        return out

    def _numeric(self) -> list[str]:
        """Columns that hold numbers (all but the trajectory's name and its part)."""
        return [k for k in self.rows[0] if k not in ("trajectory", "part")]

    def table(self) -> str:
        """The per-trajectory table (with each trajectory's part, for a family) and the mean row."""
        keys = self._numeric()
        parts = "part" in self.rows[0]
        width = max([len(r.get("part", "")) for r in self.rows] + [4]) + 2 if parts else 0
        head = f"{'trajectory':<16}" + (f"{'part':<{width}}" if parts else "")
        head += "".join(f"{k:>16}" for k in keys)
        lines = [head, "-" * len(head)]
        for r in self.rows:
            label = f"{r.get('part', ''):<{width}}" if parts else ""
            lines.append(f"{r['trajectory']:<16}" + label + "".join(f"{r[k]:>16.4f}" for k in keys))
        mean = {k: sum(r[k] for r in self.rows) / len(self.rows) for k in keys}
        lines.append("-" * len(head))
        lines.append(f"{'mean':<16}" + " " * width + "".join(f"{mean[k]:>16.4f}" for k in keys))
        return "\n".join(lines)

    def finish(self) -> dict[str, float]:
        """Write CSV, summary JSON and the RMSE-over-time plot; print the table; return the summary."""
        if not self.rows:
            raise RuntimeError("no test trajectories were rolled out")
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / "test_rmse.csv"
        table = io.StringIO(newline="")
        writer = csv.DictWriter(table, fieldnames=list(self.rows[0]))
        writer.writeheader()
        writer.writerows(self.rows)
        atomic_write_text(path, table.getvalue())
        summary = self.summary()
        atomic_write_text(self.folder / "test_summary.json", json.dumps(summary, indent=2))
        atomic_write_text(self.folder / "rmse_over_time.csv", self.over_time_csv())
        self.plot_over_time(self.folder / "rmse_over_time.png", summary)
        print("\nRollout RMSE [mm] over ply nodes, averaged over steps (model vs baselines):")
        print(self.table())
        rigid = (
            f", rigid with punch (touch radius {summary['rigid_touch_radius']:g} mm) "
            f"{summary['rigid_rmse']:.4f} mm"
            if "rigid_rmse" in summary
            else ""
        )
        print(
            f"model {summary['rollout_rmse']:.4f} mm vs best trivial baseline "
            f"{summary['baseline_rmse']:.4f} mm "
            f"(static {summary['static_rmse']:.4f} mm{rigid}): "
            f"{summary['improvement_over_baseline']:.2f}x lower"
        )
        if "setting_baseline" in summary:
            print(
                f"model {summary['rollout_rmse']:.4f} mm vs best setting-aware baseline "
                f"{summary['setting_baseline_rmse']:.4f} mm ({summary['setting_baseline']}; the mean "
                f"training trajectory {summary['mean_trajectory_rmse']:.4f} mm); explained variance of "
                f"the setting effect R^2: model {summary['setting_effect_r2']:.2f}, "
                + ", ".join(
                    f"{k} {summary[f'{k}_r2']:.2f}" for k in SETTING_BASELINES if f"{k}_r2" in summary
                )
            )
        for line in verdict(summary):
            print(line)
        print(f"wrote {path}, {self.folder / 'rmse_over_time.png'} and more in {self.folder}")
        return summary

    def over_time_csv(self) -> str:
        """CSV text: ``step`` and the mean RMSE over trajectories of the model and every baseline."""
        means = {name: torch.stack(curves).mean(0) for name, curves in self.curves.items()}  # [T+1] each
        steps = next(iter(means.values())).numel()
        lines = [",".join(["step", *means])]
        lines += [",".join([str(t), *(repr(float(m[t])) for m in means.values())]) for t in range(steps)]
        return "\n".join(lines) + "\n"

    def plot_over_time(self, path: Path, summary: dict[str, float]) -> None:
        """Write :meth:`over_time_figure` to ``path``."""
        plt = _figure()
        fig = self.over_time_figure(summary)
        atomic_savefig(fig, path)
        plt.close(fig)

    def over_time_figure(self, summary: dict[str, float]) -> Any:
        """Mean RMSE per step of the model and every baseline (thin lines: the model's single trajectories).

        The setting-aware baselines (dashed) use the training data as the model does: where one of
        them is better than the model, the picture shows it, as the table does.
        """
        plt = _figure()
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        trivial = ["static"]
        if "rigid_touch_radius" in summary:
            trivial.append(f"rigid_r{summary['rigid_touch_radius']:g}")
        aware = [k for k in SETTING_BASELINES if k in self.curves]
        styles = {"model": ("C0", "-")}
        styles.update({k: (f"C{i + 1}", ":") for i, k in enumerate(trivial)})
        styles.update({k: (f"C{i + 1 + len(trivial)}", "--") for i, k in enumerate(aware)})
        for name, (color, style) in styles.items():
            if name not in self.curves:
                continue
            curves = torch.stack(self.curves[name])[:, 1:]  # [n, T]: step 0 is the given state (error 0)
            steps = torch.arange(1, curves.size(1) + 1)
            if name == "model":
                for c in curves:
                    ax.plot(steps, c, color=color, alpha=0.25, lw=0.8)
            ax.plot(
                steps, curves.mean(0), color=color, ls=style, lw=2.5 if name == "model" else 1.6, label=name
            )
        ax.set_xlabel("step")
        ax.set_ylabel("RMSE over ply nodes [mm]")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, ncol=2)
        ax.set_title("Rollout error on the test trajectories (dashed: baselines that use the training data)")
        fig.tight_layout()
        return fig


def write_prediction(
    folder: Path, item: RolloutItem, pred: Tensor, seconds: float, xdmf: bool = True
) -> None:
    """Outputs of ``predict`` for one process setting: XDMF of the predicted rollout, a PNG, a JSON line."""
    from torch_ampn.viz import plot_laminate

    folder.mkdir(parents=True, exist_ok=True)
    predicted = dataclasses.replace(item.trajectory, pos=pred.to(item.trajectory.pos.dtype))
    if xdmf:
        from torch_ampn.data.meshio_io import export_xdmf

        export_xdmf(predicted, folder / f"{item.name}.xdmf")
    plt = _figure()
    u3 = predicted.pos[-1, :, 2] - predicted.pos[0, :, 2]
    fig = plt.figure(figsize=(7, 5.5))
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    last = plot_laminate(
        ax,
        predicted.pos[-1],
        predicted.cells,
        predicted.node_type,
        u3,
        None,
        0.0,
        show_tools=False,
        components=[0],
    )
    ax.view_init(elev=28, azim=-62)
    forces = ", ".join(f"{f:.0f}" for f in item.trajectory.gripper_force.tolist())
    where = ", ".join(f"{w:.2f}" for w in item.trajectory.meta.get("gripper_edge_fraction", []))
    ax.set_title(f"{item.name}: predicted final shape (bottom ply)\ngrippers at {where}, forces {forces} N")
    fig.colorbar(last, ax=ax, shrink=0.6, label="e3 displacement [mm]")
    atomic_savefig(fig, folder / f"{item.name}.png")
    plt.close(fig)
    info = dict(
        name=item.name,
        gripper_edge_fraction=item.trajectory.meta.get("gripper_edge_fraction"),
        gripper_force=item.trajectory.gripper_force.tolist(),
        rollout_seconds=seconds,
        max_e3_displacement_mm=float(-u3[predicted.ply_mask].min()),
    )
    atomic_write_text(folder / f"{item.name}.json", json.dumps(info, indent=2))
    print(f"predict {item.name}: {folder / (item.name + '.png')} ({seconds:.1f} s rollout)")
