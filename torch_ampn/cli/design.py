"""``torch-ampn design``: search the process settings of a dataset's part with a predictor.

    torch-ampn design data/settings --baseline pod_gp --measure wrinkle_rms --verify 16
    torch-ampn design data/settings --checkpoint best.ckpt --measure draw_in_mean=1 shear_max=0.1

The predictor is a trained surrogate (``--checkpoint``) or a setting-aware baseline fitted on
the dataset's training split (``--baseline``). Writes to ``--out``: ``design.json`` (the best
settings, their predicted measures, the top-k, the search's history and cost, the verification),
``map.png`` (the measure over two settings, the others at the best), ``fields.png`` (the
measure's field on each formed ply of the best setting: predicted, and simulated with
``--verify``), ``top_<k>.xdmf`` (the top-k predicted rollouts) and, with ``--verify``,
``verify.png`` (predicted against simulated, and the rank correlation of every measure;
``--repeat 1e-6`` adds the simulator's correlation with itself from a start moved by 1e-6 mm,
its chaos, which bounds any predictor's; ``--runs R`` judges every verified setting by its mean
over R simulations, the chaos averaged out; ``--refine STEPS`` descends from the searched best on batched
finite differences and verifies the refined setting beside it).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any


def _measure(values: list[str]) -> str | dict[str, float]:
    """``["a"]`` -> ``"a"``; ``["a=1", "b=0.5"]`` -> ``{"a": 1, "b": 0.5}``."""
    if len(values) == 1 and "=" not in values[0]:
        return values[0]
    out = {}
    for v in values:
        name, _, weight = v.partition("=")
        try:
            out[name] = float(weight or 1.0)
        except ValueError:
            raise ValueError(f"--measure {v!r}: the weight after '=' must be a number") from None
    return out


def build_predictor(args: argparse.Namespace, cfg: Any) -> tuple[Any, Any, str]:
    """The predictor the arguments name for the process ``cfg``: of the formed part, of whole rollouts.

    Returns ``(final, whole, description)``: ``final`` gives the formed part alone, ``[1, N, 3]``
    per setting, for the search, the map and the verification (a direct surrogate predicts that
    one step; see :func:`~torch_ampn.design.predictors.surrogate_predictor`); ``whole`` gives
    whole rollouts for the top-k XDMF files. A baseline's two are the same.
    """
    import torch

    from torch_ampn.design.predictors import baseline_predictor, surrogate_predictor
    from torch_ampn.training import AMPNDataModule

    if args.baseline:
        from torch_ampn.baselines import fitted_prior

        dm = AMPNDataModule(str(args.data_dir), generate=False)
        trajectories = dm.training_trajectories()
        if len(trajectories) < 2:
            raise FileNotFoundError(
                f"{args.data_dir / 'train'}: --baseline needs at least 2 training trajectories"
            )
        predict = baseline_predictor(fitted_prior(args.baseline, trajectories))
        return predict, predict, f"baseline {args.baseline}"
    from torch_ampn.training import load_module

    if not args.checkpoint.is_file():
        raise FileNotFoundError(f"{args.checkpoint}: no such checkpoint")
    module = load_module(args.checkpoint).eval()
    saved = torch.load(args.checkpoint, map_location="cpu", weights_only=False).get(
        "datamodule_hyper_parameters", {}
    )
    keep = ("prior", "prior_folds", "min_coarse_nodes", "contact_radius", "contact_k")
    dm = AMPNDataModule(
        str(args.data_dir), generate=False, max_levels=module.hparams.num_levels,
        **{k: saved[k] for k in keep if k in saved},
    )  # fmt: skip
    from torch_ampn.sim import process_trajectory

    hierarchy = dm.hierarchies(process_trajectory(cfg, seed=0))  # the mesh every setting shares
    prior = dm.prior_baseline() if getattr(module.surrogate, "prior_features", False) else None

    from torch_ampn.forming.direct import DirectSurrogate

    # a direct surrogate's V-cycle is fastest per setting in batches of 4 on a CPU (cache-bound)
    batch_size = args.batch_size or (4 if isinstance(module.surrogate, DirectSurrogate) else 8)

    def predictor(final: bool) -> Any:
        return surrogate_predictor(
            module.surrogate, hierarchy, prior, batch_size=batch_size, compile=not args.no_compile,
            final=final,
        )  # fmt: skip

    return predictor(True), predictor(False), f"surrogate {args.checkpoint}"


def run(args: argparse.Namespace) -> dict:
    """The design study the arguments describe; returns what ``design.json`` holds."""
    from torch_ampn.data.meshio_io import export_xdmf
    from torch_ampn.design import (
        MEASURES,
        SettingsSpace,
        measure_weights,
        parameter_map,
        part_quality,
        plot_measure_maps,
        plot_parameter_map,
        plot_verification,
        refine_settings,
        search_settings,
        settings_objective,
        settings_trajectories,
        verify_choice,
    )
    from torch_ampn.training import AMPNDataModule
    from torch_ampn.utils.io import atomic_write_text

    if args.batch_size is not None and args.batch_size < 1:
        raise ValueError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.runs < 1:
        raise ValueError(f"--runs must be >= 1, got {args.runs}")
    if args.runs > 1 and not args.verify:
        raise ValueError(
            f"--runs {args.runs} needs --verify N: it sets how often each verified setting is simulated"
        )
    measure = _measure(args.measure)
    try:
        names = list(measure_weights(measure))
    except ValueError as err:
        raise ValueError(f"--measure: {err}") from None
    cfg = AMPNDataModule(str(args.data_dir), generate=False).simulator_config()
    space = SettingsSpace.from_config(cfg)
    axes = tuple(space.names.index(n) if n in space.names else -1 for n in args.map)
    if len(axes) != 2 or -1 in axes or axes[0] == axes[1]:
        raise ValueError(f"--map needs two different names of {space.names}, got {args.map}")
    args.out.mkdir(parents=True, exist_ok=True)
    predict, predict_whole, described = build_predictor(args, cfg)  # predict: the formed part alone
    objective = settings_objective(predict, cfg, measure, args.wrinkle_radius)
    start = time.perf_counter()
    result = search_settings(objective, space.bounds, args.maxiter, args.popsize, args.seed, progress=True)
    search_seconds = time.perf_counter() - start
    refined = None
    if args.refine:
        start = time.perf_counter()
        refined = refine_settings(objective, space.bounds, result.best, args.refine, progress=True)
        refine_seconds = time.perf_counter() - start
    top_x, top_values = result.top(args.top)
    top_trajs = settings_trajectories(cfg, space, top_x)
    rollouts = predict_whole(top_trajs)  # whole rollouts for the XDMF files
    top, best_final = [], rollouts[0][-1]
    for k, (x, value, traj, pos) in enumerate(zip(top_x, top_values, top_trajs, rollouts, strict=True)):
        path = export_xdmf(traj, args.out / f"top_{k + 1}.xdmf", pos)
        quality = part_quality(traj, pos[-1], args.wrinkle_radius)
        top.append({"settings": dict(zip(space.names, x.tolist(), strict=True)), "objective": float(value),
                    "measures": quality, "xdmf": path.name})  # fmt: skip
    start = time.perf_counter()
    grid = parameter_map(objective, space, result.best, axes, args.map_points)
    map_seconds = time.perf_counter() - start
    label = measure if isinstance(measure, str) else "weighted measure"
    plot_parameter_map(args.out / "map.png", grid, result.best, axes, label)
    report: dict[str, Any] = {
        "data_dir": str(args.data_dir),
        "predictor": described,
        "measure": measure,
        "units": {n: MEASURES[n][0] for n in names},
        "best": top[0],
        "top": top,
        "search": {"evaluations": int(len(result.values)), "generations": result.generations,
                   "seconds": search_seconds, "seconds_per_setting": search_seconds / len(result.values),
                   "history": result.history, "maxiter": args.maxiter, "popsize": args.popsize,
                   "seed": args.seed},
        "map": {"axes": grid["axes"], "points": args.map_points, "seconds": map_seconds},
    }  # fmt: skip
    if refined is not None:
        report["refine"] = {
            "settings": dict(zip(space.names, refined.best.tolist(), strict=True)),
            "start_objective": refined.start_value, "objective": refined.best_value,
            "steps": refined.steps, "history": refined.history, "evaluations": refined.evaluations,
            "seconds": refine_seconds,
        }  # fmt: skip
    if args.verify:
        check = verify_choice(
            cfg, result.best, predict, measure, args.verify, args.seed + 1,
            compile=not args.no_compile, wrinkle_radius=args.wrinkle_radius, progress=True,
            repeat=args.repeat, runs=args.runs,
            alternatives=None if refined is None or refined.steps == 0 else {"refined": refined.best},
        )  # fmt: skip
        plot_verification(args.out / "verify.png", check, label)
        finals = check.chosen_final
        report["verify"] = check.to_dict()
        per_sim = check.simulate_seconds / ((args.verify + 1 + len(check.alternatives)) * args.runs)
        report["cost"] = {
            "search_seconds": search_seconds,
            "simulator_seconds_per_setting": per_sim,
            "search_over_simulating_the_random_settings": search_seconds / (per_sim * args.verify),
        }
    else:
        finals = {"predicted": best_final}
    weights = measure if isinstance(measure, dict) else {measure: 1.0}
    shown = max(weights, key=lambda n: abs(weights[n]))  # the heaviest measure's field
    plot_measure_maps(
        args.out / "fields.png", top_trajs[0], finals, shown, f"{shown} at the best setting (final state)"
    )
    atomic_write_text(args.out / "design.json", json.dumps(report, indent=2))
    return report


def parser() -> argparse.ArgumentParser:
    """The arguments of ``torch-ampn design``."""
    p = argparse.ArgumentParser(
        prog="torch-ampn design", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "data_dir", type=Path, help="dataset folder (its process, and its training split for baselines)"
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--checkpoint", type=Path, help="a trained surrogate's checkpoint")
    which.add_argument(
        "--baseline", choices=["mean_trajectory", "nearest_setting", "linear_settings", "pod_gp"],
        help="a setting-aware baseline fitted on the training split",
    )  # fmt: skip
    p.add_argument(
        "--measure", nargs="+", default=["wrinkle_rms"], help="NAME or NAME=WEIGHT ... (minimised)"
    )
    p.add_argument("--maxiter", type=int, default=15, help="generations of differential evolution")
    p.add_argument("--popsize", type=int, default=6, help="population per setting coordinate")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--top", type=int, default=3, help="best settings written as XDMF rollouts")
    p.add_argument("--map", nargs=2, default=["position_0", "force_0"], metavar=("X", "Y"))
    p.add_argument("--map-points", type=int, default=9)
    p.add_argument(
        "--verify", type=int, default=0, metavar="N", help="simulate the choice and N random settings"
    )
    p.add_argument(
        "--refine", type=int, default=0, metavar="STEPS",
        help="descent steps from the searched best on batched finite differences (verified too)",
    )  # fmt: skip
    p.add_argument(
        "--repeat", type=float, default=0.0, metavar="MM",
        help="with --verify: simulate the random settings again from a start moved by MM (e.g. 1e-6): "
        "the simulator's rank correlation with itself",
    )  # fmt: skip
    p.add_argument(
        "--runs", type=int, default=1, metavar="R",
        help="with --verify: simulate every setting R times (from starts moved by --repeat, default 1e-6 mm) "
        "and judge it by the mean",
    )  # fmt: skip
    p.add_argument("--wrinkle-radius", type=float, default=None, help="mm (default: 3 ply edge lengths)")
    p.add_argument(
        "--batch-size", type=int, default=None,
        help="settings per surrogate pass (default: 4 for a direct surrogate, 8 for a next-step one, "
        "which compiles one graph per size)",
    )  # fmt: skip
    p.add_argument("--no-compile", action="store_true", help="run the surrogate and the simulator eagerly")
    p.add_argument("--out", type=Path, default=Path("outputs/design"))
    return p


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv`` and run the design study; prints a short summary."""
    args = parser().parse_args(argv)
    report = run(args)
    best = report["best"]
    shown = ", ".join(f"{k} {v:.3g}" for k, v in best["settings"].items())
    print(f"best settings: {shown}; objective {best['objective']:.4g}")
    print(f"search: {report['search']['evaluations']} settings in {report['search']['seconds']:.1f} s")
    if "refine" in report:
        r = report["refine"]
        print(f"refine: {r['steps']} steps, objective {r['start_objective']:.4g} -> {r['objective']:.4g}")
    if "verify" in report:
        v = report["verify"]
        rho = "undefined (constant)" if v["spearman"] is None else f"{v['spearman']:.2f}"
        print(
            f"verify: simulated, the choice ranks {v['rank']} of {len(v['random_simulated']) + 1}; "
            f"Spearman {rho} over {len(v['random_simulated'])} random settings"
        )
        for name, alt in v["alternatives"].items():
            of = len(v["random_simulated"]) + 1
            print(f"verify: the {name} setting, simulated, ranks {alt['rank']} of {of}")
        if v["repeat"]:
            again = v["repeat_spearman"]
            again = "undefined (constant)" if again is None else f"{again:.2f}"
            moved = f"{v['repeat']:g} mm"
            print(f"verify: the simulator against itself from a start moved by {moved}: Spearman {again}")
            if v["spearman_ceiling"] is not None:
                over = f"the mean of {v['runs']} runs" if v["runs"] > 1 else "one run"
                print(
                    f"verify: a chaos-free predictor reaches about Spearman "
                    f"{v['spearman_ceiling']:.2f} against {over}"
                )
    print(f"wrote {args.out / 'design.json'}")
    return report
