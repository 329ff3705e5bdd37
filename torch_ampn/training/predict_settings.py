"""The process settings of ``torch-ampn predict``: read from a file or the command line, checked."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def read_settings(
    predict_file: str | None,
    gripper_positions: Sequence[Any] | None = None,
    gripper_forces: Sequence[Any] | None = None,
    template: bool = False,
) -> tuple[list[dict[str, Any]], str]:
    """``(settings, where they come from)``, checked.

    Each setting is a dict with ``gripper_positions`` (or, on a template, ``gripper_nodes``) and
    ``gripper_forces``.

    Args:
        predict_file: A JSON or YAML list of settings (``data.predict_file``), or ``None``.
        gripper_positions: Else one list of positions per setting (``data.predict_gripper_positions``).
        gripper_forces: And one list of forces per setting (``data.predict_gripper_forces``).
        template: Whether the settings are for a template trajectory (``gripper_nodes`` allowed).

    Raises:
        FileNotFoundError, ValueError: One line naming the file (or setting) and the field.
    """
    if predict_file:
        path = Path(predict_file)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such predict file")
        text = path.read_text()
        if path.suffix in (".yaml", ".yml"):
            import yaml

            try:
                settings = yaml.safe_load(text)
            except yaml.YAMLError as err:
                raise ValueError(f"{path}: not valid YAML ({' '.join(str(err).split())})") from None
        else:
            try:
                settings = json.loads(text)
            except json.JSONDecodeError as err:
                raise ValueError(f"{path}: not valid JSON ({err})") from None
        source = str(path)
    elif gripper_positions is not None or gripper_forces is not None:
        positions, forces = gripper_positions or [], gripper_forces or []
        if len(positions) != len(forces):
            raise ValueError(
                f"predict_gripper_positions has {len(positions)} settings, "
                f"predict_gripper_forces {len(forces)}"
            )
        settings = [
            {"gripper_positions": p, "gripper_forces": f} for p, f in zip(positions, forces, strict=True)
        ]
        source = "data.predict_gripper_positions/forces"
    else:
        raise ValueError(
            "predict needs process settings: data.predict_file, or data.predict_gripper_positions "
            "and data.predict_gripper_forces"
        )
    if not isinstance(settings, list) or not settings:
        raise ValueError(f"{source}: expected a non-empty list of settings")
    for i, s in enumerate(settings):
        where = "gripper_positions"
        if template and isinstance(s, dict) and "gripper_nodes" in s:
            where = "gripper_nodes"  # a node of the template's first ply per gripper
            if "gripper_positions" in s:
                raise ValueError(f"{source}: setting {i}: give gripper_positions or gripper_nodes, not both")
        for key in (where, "gripper_forces"):
            if not isinstance(s, dict) or key not in s:
                raise ValueError(f"{source}: setting {i} lacks field {key!r}")
            values = s[key] if isinstance(s[key], list) else [s[key]]
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
                raise ValueError(f"{source}: setting {i}, field {key!r}: expected a list of numbers")
    return settings, source
