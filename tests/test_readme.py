"""The README runs as printed: every command and code block, in order, on what the main job leaves.

The blocks are read from README.md itself. A block after ``<!-- readme-test: skip (why) -->`` is
set-up (installation, the two commands) and is not run here. The others run in a folder laid out
as the main job leaves the repository: ``examples/``, ``data/default`` and
``outputs/quickstart/checkpoints/best.ckpt``, made by ``scripts/quickstart.sh``'s own fit command
(its configs read from the script). CI's fast mode: ``data/default`` is the committed tiny dataset,
and every ``torch-ampn`` command gets a few arguments appended that shrink its work (a bash
function in front of the README's text; the text itself is unchanged).
"""

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
README = ROOT / "README.md"
#: Appended to ``torch-ampn SUBCOMMAND`` in the fast mode: the tiny dataset's splits, a few steps.
LIGHTNING_FAST = (
    "--data.data_dir data/default --data.num_train 2 --data.num_val 1 --data.num_test 1 "
    "--data.generate false --data.min_coarse_nodes 4 --trainer.max_steps 4 --trainer.val_check_interval 2 "
    "--trainer.enable_progress_bar false"
)
#: Appended too where the command's model is the next-step one (no direct.yaml): nothing compiled.
NEXT_STEP_FAST = "--model.compile_network false --model.fast_rollout false"
FAST = {
    "fit": LIGHTNING_FAST,
    "test": LIGHTNING_FAST,
    "predict": LIGHTNING_FAST,
    "design": "--maxiter 1 --popsize 2 --map-points 3 --top 1 --batch-size 3 --no-compile",
    "export": "",
}


def blocks() -> list[tuple[str, str, bool]]:
    """``(language, text, skipped)`` of every fenced block of the README, in order."""
    pattern = re.compile(r"(<!-- readme-test: skip[^>]*-->\n)?```(\w+)\n(.*?)```", re.S)
    return [(m.group(2), m.group(3), m.group(1) is not None) for m in pattern.finditer(README.read_text())]


#: Appended to the README's own-mesh block (``### AMPN on your own mesh``) where it runs: what its
#: text promises, checked in the same process (the block itself runs unchanged before it).
OWN_MESH_CHECKS = """
assert len(graphs) == 8 and all(1900 < g["l0"].num_nodes < 2200 and g.num_levels == 3 for g in graphs)
assert model.num_levels >= 2 and loss.isfinite()
assert not [n for n, _ in model.named_parameters() if "contact" in n]
print("OWN MESH CHECKED")
"""


def _own_mesh_block() -> str:
    text = README.read_text()
    section = text[text.index("### AMPN on your own mesh") :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_only_set_up_is_skipped_and_every_block_is_bash_or_python():
    skipped = [text for _, text, skip in blocks() if skip]
    assert [s.split()[:2] for s in skipped] == [["pip", "install"], ["bash", "scripts/quickstart.sh"]]
    assert {lang for lang, _, skip in blocks() if not skip} <= {"bash", "python", "bibtex"}


def _main_job_fit() -> list[str]:
    """``torch-ampn fit`` as ``scripts/quickstart.sh`` runs it: its ``configs=(...)`` array."""
    script = (ROOT / "scripts" / "quickstart.sh").read_text()
    configs = shlex.split(re.search(r"^configs=\((.*?)\)$", script, re.M).group(1))
    assert 'torch-ampn fit "${configs[@]}"' in script and configs.count("--config") >= 1
    return ["torch-ampn", "fit", *configs]


def _bash_prelude() -> str:
    """A ``torch-ampn`` function that appends the fast mode's arguments to the real command."""
    cases = "\n".join(f'    {sub}) command torch-ampn "$@" {args} ;;' for sub, args in FAST.items())
    lightning = '[[ "$1" =~ ^(fit|test|predict)$ && "$*" != *direct.yaml* ]]'
    next_step = f'  if {lightning}; then set -- "$@" {NEXT_STEP_FAST}; fi\n'
    default = '    *) command torch-ampn "$@" ;;'
    return f'torch-ampn() {{\n{next_step}  case "$1" in\n{cases}\n{default}\n  esac\n}}\n'


@pytest.mark.slow
def test_every_readme_block_runs_in_order_after_the_main_job(tiny_data, tmp_path):
    root = tmp_path / "repo"
    root.mkdir()
    (root / "examples").symlink_to(ROOT / "examples")
    shutil.copytree(tiny_data, root / "data" / "default", ignore=shutil.ignore_patterns("cache"))
    bin_dir = str(Path(sys.executable).parent)  # torch-ampn beside the test's Python
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "MPLBACKEND": "Agg"}
    env.pop("AMPN_TRACEBACK", None)

    def run(args: list[str], stdin: str | None = None) -> str:
        done = subprocess.run(args, cwd=root, env=env, input=stdin, capture_output=True, text=True)
        assert done.returncode == 0, (
            f"{args[:3]}: exit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        )
        return done.stdout

    fit = shlex.join(_main_job_fit())  # the main job, in the fast mode
    run(["bash", "-euo", "pipefail", "-c", _bash_prelude() + fit])
    assert (root / "outputs/quickstart/checkpoints/best.ckpt").is_file()

    printed = []
    for lang, text, skip in blocks():
        if skip or lang == "bibtex":
            continue
        if lang == "bash":
            printed.append(run(["bash", "-euo", "pipefail", "-c", _bash_prelude() + text]))
        else:
            checks = OWN_MESH_CHECKS if text == _own_mesh_block() else ""
            printed.append(run([sys.executable, "-"], stdin=text + checks))
    # what the README says each command leaves behind
    assert (root / "outputs/quickstart/predict").is_dir() and any(
        (root / "outputs/quickstart/predict").glob("*.json")
    )
    assert (root / "outputs/design/design.json").is_file() and (root / "outputs/model.pt").is_file()
    assert (root / "outputs/quickstart_nextstep/checkpoints/best.ckpt").is_file()
    assert "DirectSurrogate: " in "".join(printed)
    assert "OWN MESH CHECKED" in "".join(printed) and "HierarchicalData with" in "".join(printed)
