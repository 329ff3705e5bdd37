"""The README's "AMPN on your own mesh" example runs as printed (public API only, no data needed)."""

import re
from pathlib import Path

README = Path(__file__).parents[1] / "README.md"


def _block(heading: str) -> str:
    text = README.read_text()
    section = text[text.index(heading) :]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_readme_example_on_your_own_mesh_trains(capsys):
    namespace: dict = {}
    exec(compile(_block("### AMPN on your own mesh"), "README.md", "exec"), namespace)  # noqa: S102
    graphs, model = namespace["graphs"], namespace["model"]
    assert len(graphs) == 8 and all(1900 < g["l0"].num_nodes < 2200 and g.num_levels == 3 for g in graphs)
    assert model.num_levels >= 2 and "HierarchicalData with" in capsys.readouterr().out
    assert namespace["loss"].isfinite() and not [n for n, _ in model.named_parameters() if "contact" in n]
