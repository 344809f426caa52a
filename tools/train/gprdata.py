"""Training data for the learned registration model (tools/train/SPEC.md, seed 000 §4.6).

Simulates the training scenarios' runs, turns each into filtered submaps with
``graphs/submaps.yaml``, decodes them with the reference Python MCAP reader and caches the
decoded arrays as ``.npz`` (big: keep the cache out of the repo, e.g. under /tmp/train).
Then builds the registration pairs:

* ground truth (§4.6.1): any two submaps of a scenario (same or different run, pass or leg)
  whose anchors are within ``CROSS_TRACK_M`` cross-track and ``HEADING_RAD`` in heading; the
  target is the x coordinate of the query's anchor in the reference's anchor body frame,
  truth poses interpolated at the anchor stamps;
* artificial homography (§4.6.2): two submaps of the same leg, target the difference of their
  smallest wheel distances (odometry, locally accurate);
* non-overlapping: anchors more than ``APART_M`` apart (for ``share_threshold``).

The anchor of a submap is its ground-order column 0: the oldest trace (``start_stamp``) of a
forward submap, the newest (``header.stamp``) of a backward one.
"""

import os
import subprocess
from dataclasses import dataclass

import numpy as np

SCENARIO_DIR = "tools/sim/scenarios"
RUNS = ("lawnmower", "long_drive", "forward_backward")
SUBMAP_TOPIC = "/filter/submap"
TRUTH_TOPIC = "/truth/pose"

CROSS_TRACK_M = 0.25
HEADING_RAD = np.deg2rad(15.0)
MAX_TARGET_M = 1.5
APART_M = 4.0


def _stamp_ns(t):
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def _pose_row(p):
    return [p.position.x, p.position.y, p.position.z,
            p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]


def _reader(path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    f = open(path, "rb")
    return f, make_reader(f, decoder_factories=[DecoderFactory()])


def recording_path(cache_dir, scenario, run):
    return os.path.join(cache_dir, f"{scenario}-{run}.mcap")


def simulate(binary, cache_dir, scenario, run):
    """Simulates one run into ``cache_dir`` unless it is there; returns the recording."""
    out = recording_path(cache_dir, scenario, run)
    if not os.path.exists(out):
        tmp = out + ".part"
        subprocess.run([binary, "sim", os.path.join(SCENARIO_DIR, f"{scenario}.yaml"),
                        "-o", tmp, "--run", run, "--log", "warn"], check=True)
        os.replace(tmp, out)
    return out


def wheel_suffix(wheel_scale):
    """The cache names' mark of a calibrated wheel ("" for the recorded distances)."""
    return "" if wheel_scale == 1.0 else f"-w{wheel_scale:g}"


def build_submaps(binary, recording, spacing_m, wheel_scale=1.0):
    """Runs graphs/submaps.yaml over a recording unless done; returns the submap recording."""
    out = recording[: -len(".mcap")] + f"-submaps-{spacing_m:g}{wheel_suffix(wheel_scale)}.mcap"
    if not os.path.exists(out):
        tmp = out[: -len(".mcap")] + ".part.mcap"
        subprocess.run([binary, "launch", "graphs/submaps.yaml", "--set", f"recording={recording}",
                        "--set", f"spacing_m={spacing_m:g}", "--set", f"wheel_scale={wheel_scale!r}",
                        "--record", tmp, "--log", "warn"],
                       check=True)
        os.replace(tmp, out)
    return out


def decode_submaps(path):
    """The valid ``/filter/submap`` messages of a recording, as arrays (pixels as recorded)."""
    meta = {k: [] for k in ("id", "stamp_ns", "start_stamp_ns", "start_distance_m",
                            "end_distance_m", "resolution_m", "saliency", "start_pose",
                            "end_pose")}
    pixels = []
    total = 0
    f, reader = _reader(path)
    with f:
        for _, _, _, m in reader.iter_decoded_messages(topics=[SUBMAP_TOPIC]):
            total += 1
            if not m.valid:
                continue
            meta["id"].append(m.id)
            meta["stamp_ns"].append(_stamp_ns(m.header.stamp))
            meta["start_stamp_ns"].append(_stamp_ns(m.start_stamp))
            meta["start_distance_m"].append(m.start_distance_m)
            meta["end_distance_m"].append(m.end_distance_m)
            meta["resolution_m"].append(m.resolution_m)
            meta["saliency"].append(m.saliency)
            meta["start_pose"].append(_pose_row(m.start_pose))
            meta["end_pose"].append(_pose_row(m.end_pose))
            pixels.append(np.asarray(m.pixels, dtype=np.float32).reshape(m.rows, m.cols))
    out = {k: np.asarray(v) for k, v in meta.items()}
    out["pixels"] = np.stack(pixels)
    out["decoded"] = np.int64(total)
    return out


def decode_truth(path):
    """``/truth/pose``: stamps (ns) and rows ``x y z qx qy qz qw`` (world_from_body)."""
    stamps, poses = [], []
    f, reader = _reader(path)
    with f:
        for _, _, _, m in reader.iter_decoded_messages(topics=[TRUTH_TOPIC]):
            stamps.append(_stamp_ns(m.header.stamp))
            poses.append(_pose_row(m.pose))
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps, dtype=np.int64)[order], np.asarray(poses)[order]


@dataclass
class Run:
    """The valid submaps of one run, in ground order, and the truth at their anchors."""

    scenario: str
    run: str
    pixels: np.ndarray  # (n, rows, cols) f32, ground order, not standardised
    resolution_m: np.ndarray
    backward: np.ndarray  # end_distance_m < start_distance_m
    low_distance_m: np.ndarray  # min(start, end) wheel distance: the anchor's odometry
    leg: np.ndarray  # index of the straight stretch driven in one direction
    anchor_stamp_ns: np.ndarray
    anchor_position: np.ndarray  # (n, 3) truth, world
    anchor_body_x: np.ndarray  # (n, 3) truth body x axis in world
    anchor_yaw_rad: np.ndarray
    ids: np.ndarray


def ground_order(pixels, backward):
    """Columns reversed for submaps driven backwards (SPEC: column 0 = smallest body x)."""
    return np.where(backward[:, None, None], pixels[:, :, ::-1], pixels)


def standardise(image):
    """SPEC: ``(S - mean) / (std + 1e-6)`` over the whole image, population std in f64."""
    s = np.asarray(image, dtype=np.float64)
    return ((s - s.mean()) / (s.std() + 1e-6)).astype(np.float32)


def _quat_rotate_x(q):
    """The body x axis in the world for quaternions ``(qx, qy, qz, qw)`` rows."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], axis=1)


def _interpolate_truth(stamps, poses, at_ns):
    i = np.clip(np.searchsorted(stamps, at_ns), 1, len(stamps) - 1)
    t0, t1 = stamps[i - 1], stamps[i]
    a = ((at_ns - t0) / np.maximum(t1 - t0, 1)).clip(0.0, 1.0)[:, None]
    p = poses[i - 1, :3] * (1 - a) + poses[i, :3] * a
    q0, q1 = poses[i - 1, 3:], poses[i, 3:]
    q1 = np.where((q0 * q1).sum(1, keepdims=True) < 0, -q1, q1)
    q = q0 * (1 - a) + q1 * a
    return p, q / np.linalg.norm(q, axis=1, keepdims=True)


def _legs(backward, low_distance_m, yaw_rad):
    """Leg index: a new leg where the direction of travel flips or the heading turns."""
    leg = np.zeros(len(backward), dtype=np.int64)
    for i in range(1, len(backward)):
        turned = abs(np.angle(np.exp(1j * (yaw_rad[i] - yaw_rad[i - 1])))) > np.deg2rad(5.0)
        jump = abs(low_distance_m[i] - low_distance_m[i - 1]) > 0.5
        leg[i] = leg[i - 1] + int(backward[i] != backward[i - 1] or turned or jump)
    return leg


def load_run(binary, cache_dir, scenario, run, spacing_m=0.1, keep_mcap=False, wheel_scale=1.0):
    """One run's submaps and truth, decoded once and cached as ``.npz``; the submaps laid on
    the wheel's distances times ``wheel_scale`` (the rig's calibration)."""
    cache = os.path.join(cache_dir, f"{scenario}-{run}-{spacing_m:g}{wheel_suffix(wheel_scale)}.npz")
    if not os.path.exists(cache):
        rec = simulate(binary, cache_dir, scenario, run)
        sub = build_submaps(binary, rec, spacing_m, wheel_scale)
        data = decode_submaps(sub)
        data["truth_stamp_ns"], data["truth_pose"] = decode_truth(rec)
        np.savez(cache + ".part.npz", **data)
        os.replace(cache + ".part.npz", cache)
        if not keep_mcap:
            os.remove(sub)
    d = np.load(cache)
    backward = d["end_distance_m"] < d["start_distance_m"]
    anchor_ns = np.where(backward, d["stamp_ns"], d["start_stamp_ns"])
    p, q = _interpolate_truth(d["truth_stamp_ns"], d["truth_pose"], anchor_ns)
    body_x = _quat_rotate_x(q)
    yaw = np.arctan2(body_x[:, 1], body_x[:, 0])
    low = np.minimum(d["start_distance_m"], d["end_distance_m"])
    return Run(scenario=scenario, run=run,
               pixels=ground_order(d["pixels"], backward),
               resolution_m=d["resolution_m"], backward=backward, low_distance_m=low,
               leg=_legs(backward, low, yaw), anchor_stamp_ns=anchor_ns,
               anchor_position=p, anchor_body_x=body_x, anchor_yaw_rad=yaw, ids=d["id"])


@dataclass
class Pairs:
    """Registration pairs over a list of runs: submap ``(run, index)`` for each side."""

    ref_run: np.ndarray
    ref_index: np.ndarray
    query_run: np.ndarray
    query_index: np.ndarray
    target_m: np.ndarray  # NaN for non-overlapping pairs
    kind: np.ndarray  # "truth" | "homography" | "apart"
    cross_pass: np.ndarray  # different run or leg

    def __len__(self):
        return len(self.target_m)

    def gather(self, per_run, sel):
        """``(reference, query)`` stacks of ``per_run[run][index]`` for the pairs ``sel``."""
        ref = np.stack([per_run[r][i] for r, i in zip(self.ref_run[sel], self.ref_index[sel])])
        qry = np.stack([per_run[r][i] for r, i in zip(self.query_run[sel], self.query_index[sel])])
        return ref, qry

    def select(self, mask):
        return Pairs(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))

    @staticmethod
    def concat(parts):
        return Pairs(*(np.concatenate([getattr(p, f) for p in parts])
                       for f in Pairs.__dataclass_fields__))


def _pairs(ri, ii, rj, ij, target, kind, cross):
    n = len(ii)
    return Pairs(np.full(n, ri), ii, np.full(n, rj), ij, target, np.full(n, kind, dtype="<U10"),
                 np.broadcast_to(cross, (n,)).copy())


def truth_pairs(runs, rng, per_submap=4, apart_per_submap=1):
    """Ground-truth pairs (§4.6.1) and non-overlapping pairs among runs of ONE scenario.

    For every submap and run, up to ``per_submap`` random partners from other passes (another
    run or leg) and as many from its own pass among those that pass the cross-track, heading
    and shift rules, and ``apart_per_submap`` partners (from one run, in turn) whose anchors
    are more than ``APART_M`` away.
    """
    parts = []
    for ri, a in enumerate(runs):
        for rj, b in enumerate(runs):
            # relative position of every b anchor in every a anchor's frame
            dp = b.anchor_position[None, :, :] - a.anchor_position[:, None, :]
            x = (dp * a.anchor_body_x[:, None, :]).sum(-1)
            dist = np.linalg.norm(dp[..., :2], axis=-1)
            cross = np.sqrt(np.maximum(dist ** 2 - x ** 2, 0.0))
            dyaw = np.abs(np.angle(np.exp(1j * (b.anchor_yaw_rad[None, :] - a.anchor_yaw_rad[:, None]))))
            ok = (cross <= CROSS_TRACK_M) & (dyaw <= HEADING_RAD) & (np.abs(x) <= MAX_TARGET_M)
            if ri == rj:
                np.fill_diagonal(ok, False)
            apart = dist > APART_M
            other_pass = np.ones_like(ok) if ri != rj else a.leg[:, None] != b.leg[None, :]
            for i in range(len(a.ids)):
                for mask, k, target in ((ok[i] & other_pass[i], per_submap, True),
                                        (ok[i] & ~other_pass[i], per_submap, True),
                                        (apart[i] & (i % len(runs) == rj), apart_per_submap, False)):
                    js = np.flatnonzero(mask)
                    if len(js) == 0 or k == 0:
                        continue
                    js = rng.choice(js, size=min(k, len(js)), replace=False)
                    parts.append(_pairs(ri, np.full(len(js), i), rj, js,
                                        x[i, js] if target else np.full(len(js), np.nan),
                                        "truth" if target else "apart", other_pass[i, js]))
    return Pairs.concat(parts)


def homography_pairs(runs, rng, per_submap=4):
    """Artificial homography (§4.6.2): same-leg pairs, target from wheel odometry."""
    parts = []
    for ri, a in enumerate(runs):
        for i in range(len(a.ids)):
            dx = a.low_distance_m - a.low_distance_m[i]
            ok = (a.leg == a.leg[i]) & (np.abs(dx) <= MAX_TARGET_M)
            ok[i] = False
            js = np.flatnonzero(ok)
            if len(js) == 0:
                continue
            js = rng.choice(js, size=min(per_submap, len(js)), replace=False)
            parts.append(_pairs(ri, np.full(len(js), i), ri, js, dx[js], "homography", False))
    return Pairs.concat(parts)


# --- the encoder's front end (SPEC "Front end"), run before the ONNX graph ----------------------

FRONT_END_KEY = "gprflow.front_end"
FRONT_END_ITERATIONS_KEY = "gprflow.front_end.iterations"


def front_end_of(sess):
    """``("none", 0)`` or ``("band", iterations)``, as an onnxruntime session's model metadata
    names it."""
    meta = sess.get_modelmeta().custom_metadata_map
    name = meta.get(FRONT_END_KEY, "none")
    if name == "none":
        return ("none", 0)
    if name == "band":
        return ("band", int(meta[FRONT_END_ITERATIONS_KEY]))
    raise ValueError(f"unknown front end {name!r}")


def set_front_end(model, front):
    """Names ``front`` (see :func:`front_end_of`) in an ``onnx.ModelProto``'s metadata."""
    for key, value in ((FRONT_END_KEY, front[0]), (FRONT_END_ITERATIONS_KEY, str(front[1]))):
        p = model.metadata_props.add()
        p.key, p.value = key, value


def apply_front_end(front, image):
    """``image`` (standardised ``rows x cols``) through ``front`` (see :func:`front_end_of`), in
    f64, as f32: for ``band`` the largest singular component (power iteration from a flat column
    vector) taken out, then standardised again."""
    name, iterations = front
    if name == "none":
        return np.asarray(image, dtype=np.float32)
    x = np.asarray(image, dtype=np.float64)
    v = np.ones(x.shape[1])
    for _ in range(iterations):
        v = x.T @ (x @ v)
        v = v / (np.sqrt(v @ v) + 1e-12)
    y = x - np.outer(x @ v, v)
    y = y - y.mean()
    return (y / (np.sqrt((y * y).mean()) + 1e-6)).astype(np.float32)


def stretch_rows(image, factor):
    """Row ``r`` of the result is ``image`` at row ``r * factor`` (linear between rows, per column;
    0 past the last row): the register stage's travel-time stretch (stages/register/src/stretch.rs)."""
    x = np.asarray(image, dtype=np.float64)
    rows = x.shape[0]
    src = np.arange(rows) * factor
    r0 = np.minimum(np.floor(src).astype(np.int64), rows - 1)
    r1 = np.minimum(r0 + 1, rows - 1)
    a = (src - r0)[:, None]
    out = x[r0] + a * (x[r1] - x[r0])
    out[src > rows - 1] = 0.0
    return out.astype(np.float32)


def stretch_factors(step, steps):
    """``1 + k * step`` for ``k`` in ``-steps..=steps`` (the register stage's search)."""
    return [1.0 + k * step for k in range(-steps, steps + 1)]


def encode(sess, standardised, front=None):
    """Features ``K x h x w`` of one standardised submap: the front end, then the graph."""
    front = front_end_of(sess) if front is None else front
    return sess.run(None, {"submap": apply_front_end(front, standardised)[None, None]})[0][0]
