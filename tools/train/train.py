#!/usr/bin/env python3
"""Trains the learned GPR registration model (seed 000 §4.5-4.6) and exports its artefacts.

The contract with the register stage is tools/train/SPEC.md. One command does everything:
simulates the training scenarios' runs (tools/sim/scenarios/training_*.yaml, never the
evaluation worlds) unless cached, builds their filtered submaps with graphs/submaps.yaml,
decodes them (cache: ``--cache-dir``, keep it out of the repo), makes the registration pairs
(tools/train/gprdata.py), pre-trains the convolutional autoencoder with an L1 reconstruction
loss (§4.5.1), computes the spatial correlation vectors (§4.5.3), fits the linear and nonlinear
heads with a Huber loss (§4.5.4), chooses ``share_threshold`` and the channel agreement check
(§4.5.2), validates on the held-out
scenario, and writes

* stages/register/models/ground_encoding.onnx (the encoder),
* stages/register/models/ground_encoding.head.json (linear) and ...nonlinear.json,
* stages/register/tests/fixtures/learned/ (parity fixtures: manifest.json and *.f32).

Retrain (from the repository root; about 10 minutes on 2 CPU cores with the cache, another
10 the first time to simulate and decode; the defaults are the committed model's settings)::

    python3 -m venv .venv-train && .venv-train/bin/pip install -r tools/train/requirements.txt
    .venv-train/bin/python tools/train/train.py --cache-dir /tmp/train

``--data-only`` stops after simulating, building, decoding and caching the submaps (numpy and
mcap only, no torch); ``--no-export`` trains and validates without writing the artefacts;
``--calibrate`` trains nothing: it chooses the committed heads' channel agreement check and
``sigma_m`` again (as training does, from the committed ONNX encoder on the same pairs) and
rewrites the fixtures' decisions.
"""

import argparse
import datetime
import json
import math
import os
import sys
import time
import zlib

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gprdata  # noqa: E402

MODELS_DIR = "stages/register/models"
FIXTURES_DIR = "stages/register/tests/fixtures/learned"
ONNX_NAME = "ground_encoding.onnx"
HEAD_NAMES = {"linear": "ground_encoding.head.json", "nonlinear": "ground_encoding.nonlinear.json"}
OPSET = 17
MAX_SHIFT_M = 1.5
MIN_OVERLAP = 0.5
HUBER_DELTA_M = 0.05
NORM_EPS = 1e-6
PARITY_TOL = 1e-5
# the channel agreement check (SPEC "Do these two share features"): a channel agrees when its
# own shift is within AGREEMENT_TOLERANCE_M of the head's; min_fraction is chosen so that no
# training pair from another pass that passes both checks is off by more than AGREEMENT_WRONG_M
AGREEMENT_TOLERANCE_M = 0.05
AGREEMENT_WRONG_M = 0.10


def log(*parts):
    print(f"[train {time.strftime('%H:%M:%S')}]", *parts, flush=True)


# --- spatial correlation (SPEC "Spatial correlation"), numpy f64 ----------------------------

def shifts_tried(w, resolution_m, column_stride, max_shift_m=MAX_SHIFT_M, min_overlap=MIN_OVERLAP):
    """The shifts ``T`` tried (increasing) and the column size ``d`` in metres."""
    d = resolution_m * column_stride
    t_max = math.floor(max_shift_m / d)
    min_cols = math.ceil(min_overlap * w)
    ts = np.arange(-t_max, t_max + 1)
    return ts[(w - np.abs(ts)) >= min_cols], d


def correlation_curves(reference, query, ts):
    """``r_k(T)`` per SPEC, directly: ``reference``, ``query`` are ``K x h x w``; ``(K, len(ts))``."""
    ref = np.asarray(reference, dtype=np.float64)
    qry = np.asarray(query, dtype=np.float64)
    w = ref.shape[-1]
    out = np.zeros((ref.shape[0], len(ts)))
    for j, t in enumerate(ts):
        q0, q1 = max(0, -t), min(w, w - t)
        a = ref[:, :, q0 + t:q1 + t]
        b = qry[:, :, q0:q1]
        a = a - a.mean(axis=(1, 2), keepdims=True)
        b = b - b.mean(axis=(1, 2), keepdims=True)
        na = np.sqrt((a * a).sum(axis=(1, 2)))
        nb = np.sqrt((b * b).sum(axis=(1, 2)))
        ab = (a * b).sum(axis=(1, 2))
        ok = (na > 0) & (nb > 0)
        out[:, j] = np.where(ok, ab / np.where(ok, na * nb, 1.0), 0.0)
    return out


def correlation_curves_batched(reference, query, ts):
    """The same curves for a batch ``(P, K, h, w)`` of pairs, through one matrix product and prefix sums.

    ``r = (Sab - Sa Sb / n) / sqrt((Saa - Sa^2 / n) (Sbb - Sb^2 / n))``; equal to
    :func:`correlation_curves` to about 1e-12 (checked on the fixtures); for training only.
    """
    ref = np.asarray(reference, dtype=np.float64)
    qry = np.asarray(query, dtype=np.float64)
    h, w = ref.shape[-2:]
    gram = np.matmul(np.swapaxes(ref, -1, -2), qry)  # gram[i, j] = sum over rows of ref[:, i] qry[:, j]
    sab = np.stack([np.trace(gram, offset=-t, axis1=-2, axis2=-1) for t in ts], -1)  # sum_c ref[c + T] qry[c]
    pa, pb = _column_prefix(ref), _column_prefix(qry)
    paa, pbb = _column_prefix(ref * ref), _column_prefix(qry * qry)
    q0 = np.maximum(0, -ts)
    q1 = np.minimum(w, w - ts)
    n = ((q1 - q0) * h).astype(np.float64)
    sa = pa[..., q1 + ts] - pa[..., q0 + ts]
    saa = paa[..., q1 + ts] - paa[..., q0 + ts]
    sb = pb[..., q1] - pb[..., q0]
    sbb = pbb[..., q1] - pbb[..., q0]
    num = sab - sa * sb / n
    va = saa - sa * sa / n
    vb = sbb - sb * sb / n
    ok = (va > 1e-12 * np.maximum(saa, 1e-300)) & (vb > 1e-12 * np.maximum(sbb, 1e-300))
    return np.where(ok, num / np.sqrt(np.where(ok, va * vb, 1.0)), 0.0)


def _column_prefix(x):
    """Prefix sums over columns of the row sums: ``out[..., c] = sum of columns < c``."""
    col = x.sum(-2)
    return np.concatenate([np.zeros(col.shape[:-1] + (1,)), np.cumsum(col, -1)], -1)


def peaks(curves, ts, d):
    """``(tau_k, m_k)`` from curves ``(..., K, len(ts))`` (SPEC: argmax, parabola vertex)."""
    best = np.argmax(curves, axis=-1)  # first maximum: the smallest shift on ties
    m = np.take_along_axis(curves, best[..., None], -1)[..., 0]
    nb = len(ts)
    lo = np.clip(best - 1, 0, nb - 1)
    hi = np.clip(best + 1, 0, nb - 1)
    a = np.take_along_axis(curves, lo[..., None], -1)[..., 0]
    c = np.take_along_axis(curves, hi[..., None], -1)[..., 0]
    tried = (best > 0) & (best < nb - 1) & (ts[lo] == ts[best] - 1) & (ts[hi] == ts[best] + 1)
    denom = a - 2 * m + c
    ok = tried & (denom < 0)
    delta = np.where(ok, np.clip(0.5 * (a - c) / np.where(ok, denom, -1.0), -0.5, 0.5), 0.0)
    return (ts[best] + delta) * d, m


def correlation_vector(reference, query, resolution_m, column_stride):
    """SPEC's ``v = [tau_1 .. tau_K, m_1 .. m_K]`` for one pair (the reference computation)."""
    ts, d = shifts_tried(reference.shape[-1], resolution_m, column_stride)
    tau, m = peaks(correlation_curves(reference, query, ts), ts, d)
    return np.concatenate([tau, m])


def correlation_vectors(features, pairs, resolution_m, column_stride, batch=256):
    """``v`` for every pair; ``features[run][index]`` is ``K x h x w``."""
    out = []
    w = features[0].shape[-1]
    ts, d = shifts_tried(w, resolution_m, column_stride)
    for s in range(0, len(pairs), batch):
        ref, qry = pairs.gather(features, slice(s, s + batch))
        tau, m = peaks(correlation_curves_batched(ref, qry, ts), ts, d)
        out.append(np.concatenate([tau, m], axis=-1))
    return np.concatenate(out)


# --- model ------------------------------------------------------------------------------------

BAND_ITERATIONS = 6


def remove_band(submap, iterations=BAND_ITERATIONS):
    """The ``band`` front end: each submap ``(B, 1, rows, cols)`` minus its largest singular
    component (power iteration from a flat column vector), re-standardised. A horizontal band
    whose strength varies along the track (uneven ground contact) is such a component; no
    weights, part of the exported encoder graph."""
    import torch

    x = submap[:, 0]
    v = torch.ones_like(x[:, :1, :]).transpose(1, 2)  # (B, cols, 1), normalised by the first step
    for _ in range(iterations):
        v = torch.matmul(x.transpose(1, 2), torch.matmul(x, v))
        v = v / (torch.linalg.vector_norm(v, dim=1, keepdim=True) + 1e-12)
    y = x - torch.matmul(torch.matmul(x, v), v.transpose(1, 2))
    y = y - y.mean(dim=(1, 2), keepdim=True)
    y = y / (y.pow(2).mean(dim=(1, 2), keepdim=True).sqrt() + NORM_EPS)
    return y[:, None]


def build_autoencoder(channels, column_stride, levels=3, front_end="none"):
    """A small convolutional autoencoder: ``levels`` 3 x 3 convolutions of row stride 2 down
    (the first one or two also of column stride 2, for ``column_stride``), 3 up. ``front_end``
    ``band``: the encoder first applies :func:`remove_band` (and the decoder reconstructs
    that)."""
    import torch.nn as nn
    import torch.nn.functional as F

    col = ({1: (), 2: (2,), 4: (2, 2)}[column_stride] + (1,) * levels)[:levels]
    widths = (8,) * (levels - 1) + (channels,)

    class Encoder(nn.Module):
        def __init__(self):
            super().__init__()
            ins = (1,) + widths[:-1]
            self.convs = nn.ModuleList(
                nn.Conv2d(i, o, 3, stride=(2, s), padding=1) for i, o, s in zip(ins, widths, col))

        def front(self, submap):
            return remove_band(submap) if front_end == "band" else submap

        def body(self, x):
            """The convolutions: what the exported graph holds (the front end runs before it)."""
            for k, conv in enumerate(self.convs):
                x = conv(x)
                if k + 1 < len(self.convs):
                    x = F.relu(x)
            return x

        def forward(self, submap):
            return self.body(self.front(submap))

    class Decoder(nn.Module):
        """Upsample and convolve back to the input's size (the last step straight to one channel)."""

        def __init__(self):
            super().__init__()
            ins = (channels,) + (8,) * (levels - 2)
            self.convs = nn.ModuleList(nn.Conv2d(i, 8, 3, padding=1) for i in ins)
            self.out = nn.Conv2d(8, 1, 3, padding=1)

        def forward(self, features, sizes):
            x = features
            for conv, size in zip(self.convs, sizes):
                x = F.relu(conv(F.interpolate(x, size=size, mode="bilinear", align_corners=False)))
            return self.out(F.interpolate(x, size=sizes[-1], mode="bilinear", align_corners=False))

    class AutoEncoder(nn.Module):
        def __init__(self):
            super().__init__()
            self.encoder = Encoder()
            self.decoder = Decoder()

        def encode_decode(self, submap):
            """``(features, reconstruction)``."""
            sizes = []
            x = self.encoder.front(submap)
            for k, conv in enumerate(self.encoder.convs):
                sizes.append(tuple(x.shape[-2:]))
                x = conv(x)
                if k + 1 < len(self.encoder.convs):
                    x = F.relu(x)
            return x, self.decoder(x, sizes[::-1])

        def forward(self, submap):
            return self.encode_decode(submap)[1]

        def target(self, submap):
            """What the decoder reconstructs: the encoder's input after its front end."""
            return self.encoder.front(submap)

    return AutoEncoder()


def pretrain(model, images, epochs, batch, lr, rng, crop_cols=128, log_every=50):
    """L1 reconstruction (§4.5.1) on standardised submaps ``(n, rows, cols)``, random column crops."""
    import torch

    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * (len(images) // batch))
    model.train()
    step = 0
    for epoch in range(epochs):
        order = rng.permutation(len(images))
        total = 0.0
        for s in range(0, len(order) - batch + 1, batch):
            c0 = int(rng.integers(0, images.shape[-1] - crop_cols + 1))
            x = torch.from_numpy(np.ascontiguousarray(images[order[s:s + batch]][:, None, :, c0:c0 + crop_cols]))
            loss = (model(x) - model.target(x)).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
            step += 1
            if step % log_every == 0:
                log(f"autoencoder epoch {epoch} step {step} L1 {loss.item():.4f}")
        log(f"autoencoder epoch {epoch} mean L1 {total / max(1, len(order) // batch):.4f}")
    model.eval()


def torch_curves(reference, query, ts):
    """:func:`correlation_curves_batched` in torch (f64, differentiable), ``(B, K, len(ts))``."""
    import torch

    ref = reference.double()
    qry = query.double()
    h, w = ref.shape[-2:]
    tsi = torch.from_numpy(ts)
    gram = torch.matmul(ref.transpose(-1, -2), qry)
    sab = torch.stack([torch.diagonal(gram, offset=-int(t), dim1=-2, dim2=-1).sum(-1) for t in ts], -1)

    def prefix(x):
        col = x.sum(-2)
        return torch.cat([torch.zeros(col.shape[:-1] + (1,), dtype=col.dtype), torch.cumsum(col, -1)], -1)

    pa, pb, paa, pbb = prefix(ref), prefix(qry), prefix(ref * ref), prefix(qry * qry)
    q0 = torch.clamp(-tsi, min=0)
    q1 = torch.clamp(w - tsi, max=w)
    n = ((q1 - q0) * h).double()
    sa = pa[..., q1 + tsi] - pa[..., q0 + tsi]
    saa = paa[..., q1 + tsi] - paa[..., q0 + tsi]
    sb = pb[..., q1] - pb[..., q0]
    sbb = pbb[..., q1] - pbb[..., q0]
    va = torch.clamp(saa - sa * sa / n, min=1e-9)
    vb = torch.clamp(sbb - sb * sb / n, min=1e-9)
    return (sab - sa * sb / n) / torch.sqrt(va * vb)


def stretch_rows(images, scale):
    """Travel times stretched by ``scale`` (wetter soil: > 1), re-standardised; ``(B, 1, rows, cols)``."""
    import torch
    import torch.nn.functional as F

    rows = images.shape[-2]
    out = []
    for x, s in zip(images, scale):
        y = F.interpolate(x[None], size=(max(2, int(round(rows * s))), x.shape[-1]), mode="bilinear",
                          align_corners=False)[0]
        y = y[:, :rows] if y.shape[1] >= rows else F.pad(y, (0, 0, 0, rows - y.shape[1]))
        out.append((y - y.mean()) / (y.std(unbiased=False) + 1e-6))
    return torch.stack(out)


def fine_tune(model, images, pairs, mask, apart_mask, resolution_m, column_stride, steps, batch, lr, rng, recon_weight=1.0,
              temperature=0.02, apart_weight=0.1, apart_margin=0.5, cross_same_run=False):
    """Registration fine-tuning of the encoder through a soft argmax of the correlation curves.

    The argmax of SPEC is not differentiable; here each channel's curve becomes a softmax
    (``temperature``) over the shifts and its expected shift is pulled to the target (Huber),
    with the L1 reconstruction kept as a regulariser. Queries are augmented with a random
    travel-time stretch (soil moisture) and noise. Staged as in the thesis: the heads are fit
    afterwards on the hard correlation vectors. Pairs that share no ground (``apart_mask``) are
    pushed below ``apart_margin`` peak correlation, so that ``share_threshold`` separates them.
    ``cross_same_run``: the hard half of each batch only from other legs of the same run (not
    from runs at another soil moisture, which no model registers).
    """
    import torch

    idx = np.flatnonzero(mask)
    hard = mask & pairs.cross_pass & (pairs.kind == "truth")
    if cross_same_run:
        hard &= pairs.ref_run == pairs.query_run
    cross = np.flatnonzero(hard)
    apart = np.flatnonzero(apart_mask)
    w = math.ceil(images[0].shape[-1] / column_stride)
    ts, d = shifts_tried(w, resolution_m, column_stride)
    shift_m = torch.from_numpy(ts * d)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps)
    huber = torch.nn.HuberLoss(delta=HUBER_DELTA_M)
    model.train()
    for step in range(steps):
        # half the batch from other passes (other runs: other soil moisture), where it is hard
        n_cross = batch // 2 if len(cross) else 0
        sel = np.concatenate([rng.choice(cross, size=n_cross, replace=False),
                              rng.choice(idx, size=batch - n_cross, replace=False)])
        ref, qry = (torch.from_numpy(x[:, None]) for x in pairs.gather(images, sel))
        scale = np.where(rng.random(batch) < 0.5, rng.uniform(0.85, 1.18, batch), 1.0)
        qry = stretch_rows(qry, scale)
        qry = qry + float(rng.uniform(0.0, 0.3)) * torch.randn_like(qry)
        target = torch.from_numpy(pairs.target_m[sel])
        fr, rec = model.encode_decode(ref)
        fq = model.encoder(qry)
        curves = torch_curves(fr, fq, ts)
        soft = (torch.softmax(curves / temperature, -1) * shift_m).sum(-1)
        reg = huber(soft, target[:, None].expand_as(soft))
        recon = (rec - model.target(ref)).abs().mean()
        # §4.5.2: submaps that share no ground should not correlate (peaks below apart_margin)
        sel = rng.choice(apart, size=batch // 2, replace=False)
        fa, fb = (model.encoder(torch.from_numpy(x[:, None])) for x in pairs.gather(images, sel))
        apart_peak = torch_curves(fa, fb, ts).max(-1).values
        share = torch.relu(apart_peak - apart_margin).mean()
        loss = reg + recon_weight * recon + apart_weight * share
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 25 == 0 or step + 1 == steps:
            err = (soft.detach() - target[:, None]).abs().median().item() * 100
            log(f"fine-tune step {step}: registration {reg.item():.5f}, L1 {recon.item():.4f}, "
                f"apart {share.item():.4f} (mean peak {apart_peak.mean().item():.3f}), median |err| {err:.1f} cm")
    model.eval()


def heldout_l1(model, images, batch=16):
    import torch

    model.eval()
    with torch.no_grad():
        return float(np.mean([(model(x) - model.target(x)).abs().mean().item()
                              for x in (torch.from_numpy(images[s:s + batch][:, None])
                                        for s in range(0, len(images), batch))]))


def encode(encoder, images, batch=32):
    import torch

    out = []
    with torch.no_grad():
        for s in range(0, len(images), batch):
            out.append(encoder(torch.from_numpy(images[s:s + batch][:, None])).numpy())
    return np.concatenate(out)


# --- heads --------------------------------------------------------------------------------------

def fit_head(u, y, hidden, steps, lr, seed):
    """Huber-loss regression (§4.5.4) of ``y`` on normalised ``u``; returns SPEC ``layers``."""
    import torch

    torch.manual_seed(seed)
    sizes = [u.shape[1]] + list(hidden) + [1]
    lin = [torch.nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:])]
    model = torch.nn.Sequential(*sum(([l, torch.nn.ReLU()] for l in lin[:-1]), []), lin[-1]).double()
    x = torch.from_numpy(u)
    t = torch.from_numpy(y)[:, None]
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    loss_fn = torch.nn.HuberLoss(delta=HUBER_DELTA_M)
    for step in range(steps):
        loss = loss_fn(model(x), t)
        opt.zero_grad()
        loss.backward()
        opt.step()
    layers = []
    for k, l in enumerate(lin):
        layers.append({"weights": l.weight.detach().numpy().tolist(), "bias": l.bias.detach().numpy().tolist(),
                       "activation": "relu" if k + 1 < len(lin) else "none"})
    return layers, float(loss.item())


def apply_head(head, v):
    """SPEC: ``u = (v - mean) / std``, then ``u = act(W u + b)`` per layer; ``z`` in metres."""
    u = (np.asarray(v, dtype=np.float64) - head["normalise"]["mean"]) / np.asarray(head["normalise"]["std"])
    for layer in head["layers"]:
        u = u @ np.asarray(layer["weights"]).T + np.asarray(layer["bias"])
        if layer["activation"] == "relu":
            u = np.maximum(u, 0.0)
    return u[..., 0]


def choose_share_threshold(score_overlap, score_apart):
    """The mean peak that best separates overlapping from non-overlapping pairs (balanced
    accuracy); the middle of the best interval of thresholds, not its edge."""
    scores = np.unique(np.concatenate([score_overlap, score_apart]))
    over, apart = np.sort(score_overlap), np.sort(score_apart)
    # a threshold t in (scores[i - 1], scores[i]] accepts the same pairs as scores[i]
    acc = 0.5 * ((1.0 - np.searchsorted(over, scores, "left") / len(over))
                 + np.searchsorted(apart, scores, "left") / len(apart))
    start = end = int(np.argmax(acc))
    while end + 1 < len(acc) and acc[end + 1] == acc[start]:
        end += 1
    low = scores[start - 1] if start > 0 else scores[start]
    return float(0.5 * (low + scores[end])), float(acc[start])


def agreement_fraction(v, pred, k, tolerance_m=AGREEMENT_TOLERANCE_M):
    """SPEC: the fraction of the ``k`` channels whose ``tau_k`` lies within ``tolerance_m`` of
    the head's shift ``pred``, per pair."""
    return (np.abs(np.asarray(v)[..., :k] - np.asarray(pred)[..., None]) <= tolerance_m).mean(-1)


def choose_agreement(fraction, err_m, k):
    """The smallest ``min_fraction`` (a multiple of 1/k) at which none of the given pairs that
    reach it is off by more than ``AGREEMENT_WRONG_M``; 1 when there is none."""
    wrong = np.abs(err_m) > AGREEMENT_WRONG_M
    for j in range(k + 1):
        if not np.any(wrong & (fraction >= j / k)):
            return j / k
    return 1.0


def registration_decision(head, v, pred):
    """SPEC "Do these two share features", per pair: ``(shares, agreement fraction,
    registered)`` for correlation vectors ``v`` and the head's shifts ``pred``."""
    k = head["channels"]
    v = np.asarray(v)
    shares = v[..., k:].mean(-1) >= head["share_threshold"]
    frac = agreement_fraction(v, pred, k)
    check = head.get("agreement")
    return shares, frac, shares & (True if check is None else frac >= check["min_fraction"])


def write_json(path, obj):
    with open(path, "w") as f:
        json.dump(obj, f, indent=1)
        f.write("\n")


def encoder_crc32(onnx_path):
    """The head's ``encoder_crc32`` (SPEC "Head"): CRC-32 of the encoder file, 8 hex digits;
    the register stage refuses the head with any other encoder file."""
    with open(onnx_path, "rb") as f:
        return f"{zlib.crc32(f.read()):08x}"


def check_encoder(head, head_path, onnx_path):
    """Exits naming both files when ``head`` (read from ``head_path``) names another encoder
    file than ``onnx_path`` (its ``encoder_crc32``; a head without one is not checked)."""
    expected = head.get("encoder_crc32")
    if expected is not None and expected != encoder_crc32(onnx_path):
        sys.exit(f"{head_path}: encoder_crc32: {expected}, but {onnx_path} has {encoder_crc32(onnx_path)}: "
                 "the head was fitted on another encoder (give the model's encoder and head together)")


def calibrate_heads(heads, v, pairs, is_val):
    """Each head's channel agreement check (chosen on the training scenarios' truth pairs from
    other passes that pass ``share_threshold``) and ``sigma_m`` (held-out truth pairs that pass
    both checks); returns what the checks do on the held-out pairs."""
    truth = pairs.kind == "truth"
    val_truth = truth & is_val
    report = {}
    for kind, head in heads.items():
        pred = apply_head(head, v)
        shares, frac, _ = registration_decision(head, v, pred)
        pick = truth & pairs.cross_pass & shares & ~is_val
        min_fraction = choose_agreement(frac[pick], pred[pick] - pairs.target_m[pick], head["channels"])
        head["agreement"] = {
            "tolerance_m": AGREEMENT_TOLERANCE_M, "min_fraction": min_fraction,
            "rule": f"smallest multiple of 1/K at which no training truth pair from another pass that passes "
                    f"share_threshold and it is off by more than {AGREEMENT_WRONG_M} m"}
        passes = shares & (frac >= min_fraction)
        res = pred[val_truth & passes] - pairs.target_m[val_truth & passes]
        head["sigma_m"] = float(1.4826 * np.median(np.abs(res)))
        cross = val_truth & pairs.cross_pass
        report[kind] = {"min_fraction": round(min_fraction, 4),
                        "registered_fraction": round(float(passes[val_truth].mean()), 4),
                        "cross_pass_registered_fraction": round(float(passes[cross].mean()), 4),
                        "cross_pass_registered": errors_cm(pred[cross & passes], pairs.target_m[cross & passes]),
                        "cross_pass_shared": errors_cm(pred[cross & shares], pairs.target_m[cross & shares]),
                        "apart_registered_fraction": round(float(passes[is_val & (pairs.kind == "apart")].mean()), 4)}
        log(f"{kind}: agreement min_fraction {min_fraction:.4f}, sigma_m {head['sigma_m']:.4f}; held out other-pass "
            f"pairs passing share_threshold {report[kind]['cross_pass_shared']['rmse_cm']:.2f} cm RMSE, passing both "
            f"{report[kind]['cross_pass_registered']['rmse_cm']:.2f} cm on "
            f"{100 * report[kind]['cross_pass_registered_fraction']:.1f} % of them")
    return report


def errors_cm(pred, target):
    e = (np.asarray(pred) - np.asarray(target)) * 100.0
    return {"mae_cm": round(float(np.abs(e).mean()), 3), "rmse_cm": round(float(np.sqrt((e * e).mean())), 3),
            "pairs": int(len(e))}


# --- main ---------------------------------------------------------------------------------------

def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--binary", default="target/release/gprflow", help="the gprflow binary")
    p.add_argument("--cache-dir", default="/tmp/train", help="recordings and decoded .npz (big)")
    p.add_argument("--spacing-m", type=float, default=0.1, help="submap spacing for graphs/submaps.yaml")
    p.add_argument("--wheel-scale", type=float, default=1.0,
                   help="the rig's wheel calibration for graphs/submaps.yaml (the simulated rig's: 1.01002, "
                        "tools/scripts/calibrate-wheel.sh; 1: the recorded distances)")
    p.add_argument("--train-scenarios", nargs="+", default=["training_1", "training_2"])
    p.add_argument("--val-scenario", default="training_3")
    p.add_argument("--runs", nargs="+", default=list(gprdata.RUNS) + ["by_hand"],
                   help="the runs of each scenario to use (by_hand: wandering, drying, uneven ground contact)")
    p.add_argument("--channels", type=int, default=12, help="K, encoder output channels")
    p.add_argument("--levels", type=int, default=5, help="encoder convolutions (row stride 2 each)")
    p.add_argument("--column-stride", type=int, default=2, choices=(1, 2, 4))
    p.add_argument("--front-end", choices=("none", "band"), default="band",
                   help="band: the encoder first takes out each submap's largest singular component")
    p.add_argument("--epochs", type=int, default=3)
    p.add_argument("--ae-samples", type=int, default=1600, help="submaps per autoencoder epoch")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--finetune-steps", type=int, default=800, help="registration fine-tuning steps (0: none)")
    p.add_argument("--compare-pretrained", action=argparse.BooleanOptionalAction, default=False,
                   help="also fit and validate heads on the pre-trained encoder alone")
    p.add_argument("--finetune-batch", type=int, default=12)
    p.add_argument("--finetune-lr", type=float, default=5e-4)
    p.add_argument("--finetune-cross", choices=("all", "same-run"), default="same-run",
                   help="where the hard half of each fine-tuning batch comes from: other passes of any run, "
                        "or only other legs of the same run")
    p.add_argument("--hidden", type=int, default=16, help="hidden units of the nonlinear head")
    p.add_argument("--pairs-per-submap", type=int, default=2)
    p.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--data-only", action="store_true",
                   help="simulate, build, decode and cache the submaps, then stop (no torch needed)")
    p.add_argument("--no-export", action="store_true", help="train and validate, write nothing")
    p.add_argument("--stretch-steps", type=int, default=0, metavar="N",
                   help="with --calibrate: choose the checks under the register stage's travel-time stretch search "
                        "(the query also at 1 +- k * --stretch-step, k = 1..N)")
    p.add_argument("--stretch-step", type=float, default=0.015)
    p.add_argument("--calibrate", action="store_true",
                   help="no training: choose the committed heads' agreement check and sigma_m again from the "
                        "committed encoder on the same pairs, and rewrite the fixtures' decisions")
    p.add_argument("--models-dir", default=MODELS_DIR)
    p.add_argument("--fixtures-dir", default=FIXTURES_DIR)
    return p.parse_args()


def load_scenario(args, scenario):
    runs = []
    for run in args.runs:
        t = time.time()
        r = gprdata.load_run(args.binary, args.cache_dir, scenario, run, args.spacing_m, wheel_scale=args.wheel_scale)
        log(f"{scenario} {run}: {len(r.ids)} valid submaps, {r.leg.max() + 1} legs ({time.time() - t:.0f} s)")
        runs.append(r)
    return runs


def scenario_pairs(runs, rng, per_submap):
    truth = gprdata.truth_pairs(runs, rng, per_submap=per_submap, apart_per_submap=1)
    homog = gprdata.homography_pairs(runs, rng, per_submap=per_submap)
    return gprdata.Pairs.concat([truth, homog])


def load_data(args, scenarios, rng):
    """Runs (flat list), pairs per scenario (the first use of ``rng``), which pairs are held
    out, and the standardised images."""
    runs, pairs_parts = [], []
    for s in scenarios:
        sr = load_scenario(args, s)
        p = scenario_pairs(sr, rng, args.pairs_per_submap)
        p.ref_run += len(runs)
        p.query_run += len(runs)
        pairs_parts.append(p)
        runs += sr
    pairs = gprdata.Pairs.concat(pairs_parts)
    scen = np.array([r.scenario for r in runs])
    val_run = scen == args.val_scenario
    is_val = val_run[pairs.ref_run]
    resolution_m = float(runs[0].resolution_m[0])
    if any(np.any(np.abs(r.resolution_m - resolution_m) > 1e-12) for r in runs):
        sys.exit("submaps of different resolutions")
    images = [np.stack([gprdata.standardise(x) for x in r.pixels]) for r in runs]
    log(f"pairs: {len(pairs)} ({int(is_val.sum())} held out); "
        f"train truth {int(((pairs.kind == 'truth') & ~is_val).sum())} "
        f"(cross-pass {int(((pairs.kind == 'truth') & ~is_val & pairs.cross_pass).sum())}), "
        f"homography {int(((pairs.kind == 'homography') & ~is_val).sum())}, "
        f"apart {int(((pairs.kind == 'apart') & ~is_val).sum())}")
    return runs, pairs, is_val, val_run, resolution_m, images


def calibrate(args, scenarios):
    """``--calibrate``: the committed encoder (ONNX, with its front end) and heads on the same
    pairs as training; rewrites each head's agreement check and ``sigma_m`` (nothing else) and
    the parity fixtures' decisions."""
    import onnxruntime as ort

    rng = np.random.default_rng(args.seed)
    runs, pairs, is_val, _, resolution_m, images = load_data(args, scenarios, rng)
    sess = session(os.path.join(args.models_dir, ONNX_NAME))
    front = gprdata.front_end_of(sess)
    t = time.time()
    features = [np.stack([gprdata.encode(sess, x, front) for x in im]) for im in images]
    log(f"encoded {sum(len(f) for f in features)} submaps with onnxruntime {ort.__version__} ({time.time() - t:.0f} s)")
    heads = {kind: json.load(open(os.path.join(args.models_dir, name))) for kind, name in HEAD_NAMES.items()}
    t = time.time()
    v = correlation_vectors(features, pairs, resolution_m, heads["linear"]["column_stride"])
    log(f"correlation vectors {v.shape} ({time.time() - t:.0f} s)")
    if args.stretch_steps:
        v = stretch_search(sess, front, images, features, pairs, v, resolution_m, heads["linear"], args)
    report = calibrate_heads(heads, v, pairs, is_val)
    crc = encoder_crc32(os.path.join(args.models_dir, ONNX_NAME))
    for kind, head in heads.items():
        head["encoder_crc32"] = crc
        head["training"] = dict(head["training"], agreement=report,
                                calibrated={"date": datetime.date.today().isoformat(),
                                            "command": "python " + " ".join(["tools/train/train.py"] + sys.argv[1:])})
        head["training"]["sigma_rule"] = ("1.4826 x median |residual| on held-out truth pairs that pass share_threshold "
                                          "and the agreement check")
        write_json(os.path.join(args.models_dir, HEAD_NAMES[kind]), head)
    manifest_path = os.path.join(args.fixtures_dir, "manifest.json")
    manifest = json.load(open(manifest_path))
    for case in manifest["cases"]:
        case.update(fixture_decision(heads["linear"], np.asarray(case["correlation"]), case["linear_m"]))
    write_json(manifest_path, manifest)
    log(f"wrote {', '.join(HEAD_NAMES.values())} and {manifest_path}")


def stretch_search(sess, front, images, features, pairs, v, resolution_m, head, args):
    """The register stage's travel-time stretch search (``stretch_steps``, docs/localisation.md)
    on every pair: the query's rows stretched by each factor, and the correlation vector with
    the highest mean channel peak kept (the query stretched after standardising; the stage stretches
    it before, which differs only in the last rows, past the end of the image)."""
    k = head["channels"]
    for factor in gprdata.stretch_factors(args.stretch_step, args.stretch_steps):
        if factor == 1.0:
            continue
        t = time.time()
        stretched = [f.copy() for f in features]
        for r, im in enumerate(images):
            for i in np.unique(pairs.query_index[pairs.query_run == r]):
                stretched[r][i] = gprdata.encode(sess, gprdata.standardise(gprdata.stretch_rows(im[i], factor)), front)
        # the reference side unstretched, the query side stretched
        n_runs = len(features)
        on_stretched = gprdata.Pairs(pairs.ref_run, pairs.ref_index, pairs.query_run + n_runs, pairs.query_index,
                                     pairs.target_m, pairs.kind, pairs.cross_pass)
        w = correlation_vectors(features + stretched, on_stretched, resolution_m, head["column_stride"])
        better = w[:, k:].mean(-1) > v[:, k:].mean(-1)
        v = np.where(better[:, None], w, v)
        log(f"stretch {factor:g}: better for {100 * better.mean():.1f} % of the pairs ({time.time() - t:.0f} s)")
    return v


def fixture_decision(head, v, linear_m):
    """A fixture case's decision fields: ``shares`` (share_threshold), ``agreement`` (the
    fraction of channels agreeing with the linear head) and ``registered`` (both checks)."""
    shares, frac, registered = registration_decision(head, v, np.asarray(linear_m))
    return {"shares": bool(shares), "agreement": float(frac), "registered": bool(registered)}


def main():
    args = parse_args()
    os.makedirs(args.cache_dir, exist_ok=True)
    scenarios = args.train_scenarios + [args.val_scenario]
    if any(not s.startswith("training_") for s in scenarios):
        sys.exit("only the simulator's training scenarios (training_*) may be used")
    if args.data_only:
        for s in scenarios:
            load_scenario(args, s)
        return
    if args.calibrate:
        calibrate(args, scenarios)
        return

    import torch

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    started = time.time()
    runs, pairs, is_val, val_run, resolution_m, images = load_data(args, scenarios, rng)

    # §4.5.1: autoencoder on the training scenarios' submaps
    train_images = np.concatenate([im for im, v in zip(images, val_run) if not v])
    ae = build_autoencoder(args.channels, args.column_stride, args.levels, args.front_end)
    t = time.time()
    pick = rng.choice(len(train_images), size=min(args.ae_samples, len(train_images)), replace=False)
    pretrain(ae, train_images[pick], args.epochs, args.batch, args.lr, rng)
    ae_seconds = time.time() - t
    del train_images
    val_images = np.concatenate([im[::max(1, len(im) // 40)] for im, v in zip(images, val_run) if v])
    val_l1 = heldout_l1(ae, val_images)
    log(f"autoencoder: {ae_seconds:.0f} s, held-out L1 {val_l1:.4f}")

    val_truth = is_val & (pairs.kind == "truth")
    engineered, _ = engineered_baseline(images, pairs, val_truth, resolution_m)
    fit = {}
    if args.finetune_steps > 0 and args.compare_pretrained:
        log("heads on the pre-trained encoder alone, for comparison:")
        fit["pretrained"] = fit_and_validate(ae.encoder.eval(), images, pairs, is_val, resolution_m, engineered, args)
    finetune_seconds = 0.0
    if args.finetune_steps > 0:
        t = time.time()
        fine_tune(ae, images, pairs, (pairs.kind != "apart") & ~is_val, (pairs.kind == "apart") & ~is_val,
                  resolution_m, args.column_stride,
                  args.finetune_steps, args.finetune_batch, args.finetune_lr, rng,
                  cross_same_run=args.finetune_cross == "same-run")
        finetune_seconds = time.time() - t
    val_l1_tuned = heldout_l1(ae, val_images)
    log(f"after fine-tuning: {finetune_seconds:.0f} s, held-out L1 {val_l1_tuned:.4f}")
    encoder = ae.encoder.eval()
    final = fit_and_validate(encoder, images, pairs, is_val, resolution_m, engineered, args)
    heads = final["heads"]

    counts = {"train": {kd: int(((pairs.kind == kd) & ~is_val).sum()) for kd in ("truth", "homography", "apart")},
              "held_out": {kd: int(((pairs.kind == kd) & is_val).sum()) for kd in ("truth", "homography", "apart")}}
    counts["train"]["truth_cross_pass"] = int(((pairs.kind == "truth") & ~is_val & pairs.cross_pass).sum())
    counts["held_out"]["truth_cross_pass"] = int(((pairs.kind == "truth") & is_val & pairs.cross_pass).sum())
    training = {"scenarios": {"train": args.train_scenarios, "held_out": args.val_scenario, "runs": list(args.runs)},
                "submaps": {"spacing_m": args.spacing_m, "wheel_scale": args.wheel_scale, "valid": {r.scenario + "/" + r.run: int(len(r.ids)) for r in runs}},
                "pairs": counts,
                "pair_rules": {"cross_track_m": gprdata.CROSS_TRACK_M, "heading_deg": 15.0,
                               "max_target_m": gprdata.MAX_TARGET_M, "apart_m": gprdata.APART_M},
                "autoencoder": {"loss": "L1", "front_end": args.front_end, "epochs": args.epochs, "submaps_per_epoch": int(len(pick)),
                                "crop_cols": 128, "held_out_l1": round(val_l1, 5), "seconds": round(ae_seconds, 1)},
                "fine_tune": {"steps": args.finetune_steps, "batch": args.finetune_batch, "lr": args.finetune_lr,
                              "cross": args.finetune_cross,
                              "loss": "huber of the soft-argmax shift per channel + L1 reconstruction",
                              "augmentation": "query travel times stretched x0.85..1.18 (half the pairs), noise",
                              "held_out_l1": round(val_l1_tuned, 5), "seconds": round(finetune_seconds, 1)},
                "head_loss": f"huber delta {HUBER_DELTA_M} m",
                "share_threshold": final["share"],
                "validation_held_out_truth_pairs": final["report"],
                "sigma_rule": "1.4826 x median |residual| on held-out truth pairs that pass share_threshold and "
                              "the agreement check",
                "date": datetime.date.today().isoformat(),
                "command": "python " + " ".join(["tools/train/train.py"] + sys.argv[1:]),
                "seed": args.seed}
    if "pretrained" in fit:
        training["validation_pretrained_encoder_only"] = fit["pretrained"]["report"]
    for head in heads.values():
        head["training"] = training
    log(f"total {time.time() - started:.0f} s")
    if args.no_export:
        return
    export(args, encoder, heads, images, runs, pairs, is_val, resolution_m)


def fit_and_validate(encoder, images, pairs, is_val, resolution_m, engineered, args):
    """Correlation vectors, ``share_threshold``, both heads and their held-out errors."""
    t = time.time()
    features = [encode(encoder, im) for im in images]
    k, h, w = features[0].shape[1:]
    if w != math.ceil(images[0].shape[-1] / args.column_stride):
        sys.exit(f"encoder width {w} is not ceil(cols / column_stride)")
    v = correlation_vectors(features, pairs, resolution_m, args.column_stride)
    del features
    log(f"features K={k} h={h} w={w}; correlation vectors {v.shape} ({time.time() - t:.0f} s)")
    np.savez(os.path.join(args.cache_dir, "last-correlation-vectors.npz"), v=v, is_val=is_val,
             **{f: getattr(pairs, f) for f in pairs.__dataclass_fields__})

    overlap = pairs.kind != "apart"
    train_fit = overlap & ~is_val
    mean_peak = v[:, k:].mean(1)
    mean = v[train_fit].mean(0)
    std = v[train_fit].std(0)
    std = np.where(std > NORM_EPS, std, 1.0)
    u = (v - mean) / std
    y = np.where(overlap, pairs.target_m, 0.0)
    zeroth = float(y[train_fit].mean())

    share_threshold, share_acc = choose_share_threshold(mean_peak[train_fit], mean_peak[~overlap & ~is_val])
    val_share = 0.5 * ((mean_peak[overlap & is_val] >= share_threshold).mean()
                       + (mean_peak[~overlap & is_val] < share_threshold).mean())
    log(f"share_threshold {share_threshold:.4f} (train balanced accuracy {share_acc:.3f}, held out {val_share:.3f})")

    # §4.5.4: heads
    common = {"format": "gprflow-register-head", "version": 1, "channels": int(k),
              "column_stride": args.column_stride, "max_shift_m": MAX_SHIFT_M, "min_overlap": MIN_OVERLAP,
              "normalise": {"mean": mean.tolist(), "std": std.tolist()}}
    heads = {}
    for kind, hidden, steps, lr in (("linear", [], 3000, 0.01), ("nonlinear", [args.hidden], 4000, 0.005)):
        layers, loss = fit_head(u[train_fit], y[train_fit], hidden, steps, lr, args.seed)
        heads[kind] = dict(common, kind=kind, layers=layers)
        log(f"{kind} head: train Huber {loss:.6f}")

    # validation: held-out ground-truth pairs
    val_truth = is_val & (pairs.kind == "truth")
    shares = mean_peak >= share_threshold
    subsets = {"all": val_truth, "cross_pass": val_truth & pairs.cross_pass,
               "same_pass": val_truth & ~pairs.cross_pass,
               "other_run": val_truth & (pairs.ref_run != pairs.query_run), "shared": val_truth & shares,
               "cross_pass_shared": val_truth & pairs.cross_pass & shares}
    preds = {"engineered": engineered, "zeroth": np.full(len(pairs), zeroth),
             "linear": apply_head(heads["linear"], v), "nonlinear": apply_head(heads["nonlinear"], v)}
    report = {}
    for name, mask in subsets.items():
        report[name] = {m: errors_cm(p[mask], pairs.target_m[mask]) for m, p in preds.items()}
    report["shared_fraction"] = round(float(shares[val_truth].mean()), 4)
    report["apart_rejected_fraction"] = round(float((~shares[is_val & ~overlap]).mean()), 4)
    for name in subsets:
        log(f"held out {name}: " + ", ".join(f"{m} {e['mae_cm']:.2f}/{e['rmse_cm']:.2f}" for m, e in report[name].items())
            + f" cm (MAE/RMSE, {report[name]['zeroth']['pairs']} pairs)")
    log(f"held out: {report['shared_fraction']:.3f} of truth pairs pass share_threshold, "
        f"{report['apart_rejected_fraction']:.3f} of non-overlapping pairs rejected")
    for head in heads.values():
        head.update(share_threshold=share_threshold, zeroth_m=zeroth)
    report["agreement"] = calibrate_heads(heads, v, pairs, is_val)
    share = {"train_balanced_accuracy": round(share_acc, 4), "held_out_balanced_accuracy": round(float(val_share), 4)}
    return {"heads": heads, "report": report, "share": share}


def engineered_baseline(images, pairs, mask, resolution_m, batch=64):
    """Eq. 4.2-4.3 on the standardised submaps (stride 1, SPEC shift rules), for comparison:
    ``(shift_m, peak)`` for the pairs in ``mask`` (NaN elsewhere)."""
    out, peak = np.full(len(pairs), np.nan), np.full(len(pairs), np.nan)
    idx = np.flatnonzero(mask)
    w = images[0].shape[-1]
    ts, d = shifts_tried(w, resolution_m, 1)
    for s in range(0, len(idx), batch):
        sl = idx[s:s + batch]
        ref, qry = (x[:, None] for x in pairs.gather(images, sl))
        tau, m = peaks(correlation_curves_batched(ref, qry, ts), ts, d)
        out[sl], peak[sl] = tau[:, 0], m[:, 0]
    return out, peak


# --- export -------------------------------------------------------------------------------------

def export(args, encoder, heads, images, runs, pairs, is_val, resolution_m):
    import onnxruntime as ort
    import torch

    os.makedirs(args.models_dir, exist_ok=True)
    onnx_path = os.path.join(args.models_dir, ONNX_NAME)
    example = torch.from_numpy(images[0][:1][:, None])

    class Graph(torch.nn.Module):
        """The encoder's convolutions; its front end runs before the graph (SPEC "Front end")."""

        def __init__(self):
            super().__init__()
            self.encoder = encoder

        def forward(self, x):
            return self.encoder.body(x)

    torch.onnx.export(Graph(), (example,), onnx_path, input_names=["submap"], output_names=["features"],
                      dynamic_axes={"submap": {2: "rows", 3: "cols"}, "features": {2: "h", 3: "w"}},
                      opset_version=OPSET, dynamo=False)
    import onnx

    model = onnx.load(onnx_path)
    front = ("band", BAND_ITERATIONS) if args.front_end == "band" else ("none", 0)
    gprdata.set_front_end(model, front)
    onnx.checker.check_model(model)
    onnx.save(model, onnx_path)
    sess = session(onnx_path)
    if gprdata.front_end_of(sess) != front:
        sys.exit(f"exported front end {gprdata.front_end_of(sess)}, expected {front}")
    # torch (front end and convolutions) vs numpy front end + onnxruntime, at the real size and
    # at odd sizes
    for shape in ((1, 1) + images[0].shape[1:], (1, 1, 150, 173), (1, 1, 64, 31)):
        x = np.random.default_rng(0).standard_normal(shape).astype(np.float32)
        with torch.no_grad():
            ref = encoder(torch.from_numpy(x)).numpy()
        got = gprdata.encode(sess, x[0, 0], front)[None]
        if got.shape[-1] != math.ceil(shape[-1] / args.column_stride):
            sys.exit(f"onnx width {got.shape} for {shape}")
        err = np.abs(got - ref).max() / np.abs(ref).max()
        log(f"onnx vs torch {shape}: max rel err {err:.2e}")
        if err > PARITY_TOL:
            sys.exit("onnx does not match torch")
    ms = time_encoder(onnx_path, images[0][0])
    log(f"onnxruntime {ort.__version__}, 1 intra-op thread, {images[0].shape[1]} x {images[0].shape[2]}: "
        f"median {ms['median_ms']:.3f} ms, p90 {ms['p90_ms']:.3f} ms")
    for kind, head in heads.items():
        head["encoder_crc32"] = encoder_crc32(onnx_path)
        head["training"] = dict(head["training"], onnx_ms_one_thread=ms, onnx_bytes=os.path.getsize(onnx_path))
        write_json(os.path.join(args.models_dir, HEAD_NAMES[kind]), head)
    write_fixtures(args, sess, heads, runs, pairs, is_val, resolution_m)


def session(path):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def time_encoder(path, image, runs=300):
    """The graph alone (without the front end, which runs in Rust)."""
    sess = session(path)
    x = image[None, None].astype(np.float32)
    for _ in range(30):
        sess.run(None, {"submap": x})
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        sess.run(None, {"submap": x})
        ts.append(time.perf_counter() - t)
    return {"median_ms": round(float(np.median(ts)) * 1e3, 4), "p90_ms": round(float(np.percentile(ts, 90)) * 1e3, 4),
            "runs": runs}


def write_fixtures(args, sess, heads, runs, pairs, is_val, resolution_m):
    """Four held-out cases at real size: one leg, two legs, two runs, no shared ground."""
    out_dir = args.fixtures_dir
    os.makedirs(out_dir, exist_ok=True)
    for f in os.listdir(out_dir):
        if f.endswith(".f32") or f == "manifest.json":
            os.remove(os.path.join(out_dir, f))
    stride = args.column_stride
    lin, non = heads["linear"], heads["nonlinear"]
    rng = np.random.default_rng(args.seed + 7)
    wanted = (
        ("same_leg_shift", "one leg of one pass (held-out scenario), a known shift (truth target)",
         is_val & (pairs.kind == "truth") & ~pairs.cross_pass & (np.abs(pairs.target_m) > 0.3)),
        ("different_legs", "two passes of one run over the same ground, one driven backwards (held-out scenario)",
         is_val & (pairs.kind == "truth") & pairs.cross_pass & (pairs.ref_run == pairs.query_run)
         & (np.abs(pairs.target_m) > 0.2)),
        ("different_runs", "two runs (other soil moisture) over the same ground (held-out scenario)",
         is_val & (pairs.kind == "truth") & (pairs.ref_run != pairs.query_run) & (np.abs(pairs.target_m) > 0.2)),
        ("non_overlapping", "anchors more than 4 m apart: no shared ground",
         is_val & (pairs.kind == "apart")),
    )
    cases = []
    for name, description, mask in wanted:
        case = None
        # a pair the model registers (or rejects) correctly, when there is one
        for want_right in (True, False):
            for j in rng.permutation(np.flatnonzero(mask))[:200]:
                case = fixture_case(sess, runs, pairs, j, resolution_m, stride, lin, non)
                if case is not None and (not want_right or registered_right(case[0])):
                    break
                case = None
            if case is not None:
                break
        if case is None:
            sys.exit(f"no fixture for {name}")
        entry, arrays = case
        entry = dict(name=name, description=description, **entry)
        for role, arr in arrays.items():
            file = f"{name}.{role}.f32"
            arr.astype("<f4").tofile(os.path.join(out_dir, file))
            entry[role] = dict(entry.get(role, {}), file=file)
        cases.append(entry)
        log(f"fixture {name}: target {entry['target_m']}, linear {entry['linear_m']:.4f}, "
            f"nonlinear {entry['nonlinear_m']:.4f}, mean peak {entry['mean_peak']:.4f}")
    manifest = {"format": "gprflow-learned-fixtures", "version": 1,
                "model": f"stages/register/models/{ONNX_NAME}",
                "heads": {kind: f"stages/register/models/{name}" for kind, name in HEAD_NAMES.items()},
                "tolerance": PARITY_TOL,
                "tolerance_rule": "max |got - expected| <= tolerance x max |expected|, per array",
                "onnxruntime": __import__("onnxruntime").__version__,
                "regenerate": "tools/train/train.py (see its docstring)",
                "cases": cases}
    write_json(os.path.join(out_dir, "manifest.json"), manifest)


PEAK_MARGIN = 1e-4
RIGHT_M = 0.03


def registered_right(entry):
    """Registered within ``RIGHT_M`` of the truth, or rejected when there is no truth."""
    if entry["target_m"] is None:
        return not entry["registered"]
    return entry["registered"] and abs(entry["linear_m"] - entry["target_m"]) < RIGHT_M


def fixture_case(sess, runs, pairs, j, resolution_m, stride, lin, non):
    """One case, or None when an argmax is too close to a tie to be a fair parity test."""
    ref_px = runs[pairs.ref_run[j]].pixels[pairs.ref_index[j]]
    qry_px = runs[pairs.query_run[j]].pixels[pairs.query_index[j]]
    fr = gprdata.encode(sess, gprdata.standardise(ref_px))
    fq = gprdata.encode(sess, gprdata.standardise(qry_px))
    ts, d = shifts_tried(fr.shape[-1], resolution_m, stride)
    curves = correlation_curves(fr, fq, ts)
    fast = correlation_curves_batched(fr[None], fq[None], ts)[0]
    if np.abs(fast - curves).max() > 1e-9:
        sys.exit(f"batched correlation differs from the direct one by {np.abs(fast - curves).max():.2e}")
    top2 = np.sort(curves, axis=-1)[:, -2:]
    if np.any(top2[:, 1] - top2[:, 0] < PEAK_MARGIN):
        return None
    v = correlation_vector(fr, fq, resolution_m, stride)
    k = fr.shape[0]
    target = pairs.target_m[j]
    entry = {"rows": int(ref_px.shape[0]), "cols": int(ref_px.shape[1]), "resolution_m": resolution_m,
             "reference": {"scenario": runs[pairs.ref_run[j]].scenario, "run": runs[pairs.ref_run[j]].run,
                           "submap_id": int(runs[pairs.ref_run[j]].ids[pairs.ref_index[j]])},
             "query": {"scenario": runs[pairs.query_run[j]].scenario, "run": runs[pairs.query_run[j]].run,
                       "submap_id": int(runs[pairs.query_run[j]].ids[pairs.query_index[j]])},
             "features_shape": [int(s) for s in fr.shape],
             "target_m": None if np.isnan(target) else float(target),
             "correlation": v.tolist(), "mean_peak": float(v[k:].mean()),
             "linear_m": float(apply_head(lin, v)), "nonlinear_m": float(apply_head(non, v))}
    entry.update(fixture_decision(lin, v, entry["linear_m"]))
    arrays = {"reference": ref_px, "query": qry_px, "reference_features": fr, "query_features": fq}
    return entry, arrays


if __name__ == "__main__":
    main()
