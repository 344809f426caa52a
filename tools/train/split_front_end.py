"""Moves a ``band`` front end out of an encoder graph exported before train.py ran it outside
(``--front-end band`` models up to 2026-12-02): the weight-free nodes before the first
convolution are dropped, the convolution reads the graph input ``submap``, and the model's
metadata names the front end (``gprflow.front_end = band``, ``gprflow.front_end.iterations``)
so that the register stage runs it in Rust (SPEC "Front end"). The weights stay as they are.

Checks that the new graph after :func:`gprdata.apply_front_end` gives the old graph's features
to 1e-5 (relative) on random submaps and on the parity fixtures' submaps, then writes the
model in place (or to ``--out``).

usage: split_front_end.py [MODEL.onnx] [--iterations 6] [--out NEW.onnx]
"""

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gprdata  # noqa: E402

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
TOLERANCE = 1e-5


def split(model, iterations):
    """The graph without its front end (a new ``onnx.ModelProto``)."""
    import onnx

    m = onnx.ModelProto()
    m.CopyFrom(model)
    g = m.graph
    if any(p.key == gprdata.FRONT_END_KEY for p in m.metadata_props):
        sys.exit("the model already names its front end in its metadata")
    first = next((i for i, n in enumerate(g.node) if n.op_type == "Conv"), None)
    if first is None:
        sys.exit("no convolution in the graph")
    matmuls = sum(n.op_type == "MatMul" for n in g.node[:first])
    if matmuls != 2 * iterations + 2:
        sys.exit(f"{matmuls} MatMul nodes before the first convolution: not a band front end of "
                 f"{iterations} iterations (expected {2 * iterations + 2})")
    g.node[first].input[0] = g.input[0].name
    needed, kept = {o.name for o in g.output}, []
    for n in reversed(list(g.node)):
        if any(o in needed for o in n.output):
            kept.append(n)
            needed.update(n.input)
    del g.node[:]
    g.node.extend(reversed(kept))
    gprdata.set_front_end(m, ("band", iterations))
    onnx.checker.check_model(m)
    return m


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", nargs="?", default=os.path.join(ROOT, "stages/register/models/ground_encoding.onnx"))
    p.add_argument("--iterations", type=int, default=6)
    p.add_argument("--out")
    args = p.parse_args()
    import onnx
    import onnxruntime as ort

    old = onnx.load(args.model)
    new = split(old, args.iterations)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    sessions = [ort.InferenceSession(m.SerializeToString(), so) for m in (old, new)]
    rng = np.random.default_rng(0)
    images = [rng.standard_normal(s).astype(np.float32) for s in ((201, 200), (150, 173), (64, 31))]
    fixtures = os.path.join(ROOT, "stages/register/tests/fixtures/learned")
    for case in json.load(open(os.path.join(fixtures, "manifest.json")))["cases"]:
        for role in ("reference", "query"):
            px = np.fromfile(os.path.join(fixtures, case[role]["file"]), dtype="<f4")
            images.append(px.reshape(case["rows"], case["cols"]))
    worst = 0.0
    for image in images:
        x = gprdata.standardise(image)
        want = sessions[0].run(None, {"submap": x[None, None]})[0]
        got = gprdata.encode(sessions[1], x)[None]
        worst = max(worst, float(np.abs(got - want).max() / np.abs(want).max()))
    print(f"{len(images)} submaps: front end + new graph vs old graph, max relative error {worst:.2e}")
    if worst > TOLERANCE:
        sys.exit(f"differs by more than {TOLERANCE:.0e}: model left as it was")
    out = args.out or args.model
    onnx.save(new, out)
    print(f"wrote {out} ({os.path.getsize(out)} bytes, {len(new.graph.node)} nodes)")


if __name__ == "__main__":
    main()
