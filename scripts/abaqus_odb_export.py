"""Write an Abaqus ODB's nodal displacements as the table ``torch-ampn-data convert`` reads.

Runs in Abaqus's own Python (2.7 or 3, so no f-strings here), which has NumPy but not torch-ampn:

    abaqus python scripts/abaqus_odb_export.py forming.odb            # -> forming.npz
    abaqus python scripts/abaqus_odb_export.py forming.odb --step Forming --out run0.npz

then, with the flat input deck of the same run and a part map keyed by element set names:

    torch-ampn-data convert forming.inp --parts parts.yaml --out data/mine/train/run0.pt

The table (``numpy.savez``): ``node_labels [N]`` (the deck's node numbers), ``time [T+1]``
(total time of every saved frame, s) and ``u [T+1, N, 3]`` (nodal ``U``; zero where a frame
has none, 2D output padded). Frames of every step in order (or of the ``--step`` ones); a
step's first frame repeats the previous step's last and is left out. Request ``U`` on the
tools' nodes too (field output ``U`` for the whole model).
"""

import argparse
import os
import sys

import numpy as np


def export(odb_path, out_path, step_names=None, open_odb=None):
    """Write ``out_path`` (``.npz``) from the ODB at ``odb_path``; returns the number of frames."""
    if open_odb is None:
        from odbAccess import openOdb as open_odb  # only inside Abaqus
    odb = open_odb(odb_path, readOnly=True)
    instances = odb.rootAssembly.instances
    labels = []
    for name in instances.keys():
        labels.extend(node.label for node in instances[name].nodes)
    if len(set(labels)) != len(labels):
        raise SystemExit(
            "{}: node labels repeat across instances {}: export a flat deck's run (Model > Edit "
            "Attributes > Do not use parts and assemblies in input files)".format(
                odb_path, list(instances.keys())
            )
        )
    row = dict((label, k) for k, label in enumerate(labels))
    names = step_names or list(odb.steps.keys())
    times, frames = [], []
    for s, name in enumerate(names):
        if name not in odb.steps.keys():
            raise SystemExit("{}: no step {!r} (steps: {})".format(odb_path, name, list(odb.steps.keys())))
        step = odb.steps[name]
        for f, frame in enumerate(step.frames):
            if s > 0 and f == 0:
                continue  # the previous step's last state again
            u = np.zeros((len(labels), 3))
            if "U" in frame.fieldOutputs.keys():
                for value in frame.fieldOutputs["U"].values:
                    k = row.get(value.nodeLabel)
                    if k is not None:
                        data = list(value.data)
                        u[k, : len(data)] = data
            times.append(step.totalTime + frame.frameValue)
            frames.append(u)
    odb.close()
    if len(frames) < 2:
        raise SystemExit("{}: {} saved frames; at least 2 needed".format(odb_path, len(frames)))
    tmp = out_path + ".tmp.npz"
    np.savez(tmp, node_labels=np.array(labels, dtype=np.int64), time=np.array(times), u=np.array(frames))
    getattr(os, "replace", os.rename)(tmp, out_path)  # Python 2.7 has no os.replace
    return len(frames)


def main(argv=None):
    """The command line: ``abaqus python abaqus_odb_export.py RUN.odb [--out T.npz] [--step S]``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("odb")
    parser.add_argument("--out", default=None, help="the table (default: the ODB's name with .npz)")
    parser.add_argument("--step", action="append", default=None, help="only these steps (repeatable)")
    args = parser.parse_args(argv)
    out = args.out or os.path.splitext(args.odb)[0] + ".npz"
    count = export(args.odb, out, args.step)
    print("wrote {}: {} frames".format(out, count))
    return 0


if __name__ == "__main__":
    sys.exit(main())
