"""Fairness check of a capture: can its appearance states be predicted from the pose, or from the pose history?

One simple regressor (ridge regression on PCA-reduced pose features, its regularisation and its number of PCA
components chosen by cross-validation over contiguous blocks of the training frames) is fit twice on the training
frames:

- ``pose_only``: features of the current frame ``t`` alone;
- ``history``: the same features of frames ``t-N+1..t`` (clamped at the sequence start), given to the
  regressor as frame ``t``'s features and the ``N-1`` frame-to-frame changes (:func:`history_features`: an
  invertible linear map of the stacked frames, so the same information; each column is standardised before
  the ridge, so its shrinkage acts on the motion, not on ``N`` near-copies of the pose).

Each state gets its own regularisation and number of components (:data:`COMPONENTS`: a pose read from 12
components missed what a periodic motion's pose tells of a spring's phase, docs/synth.md), predictions are clipped
to the training range of each state, and both are scored on the test frames by R^2 pooled over the (standardised)
states: ``1 - sum SSE / sum SST``, SST around the test frames' own mean. A capture whose appearance the motion
history causes has ``history`` clearly above ``pose_only``; one whose appearance is random in time has both near or
below 0. Per frame the features are the joint-local pose parameters and the joints' root-relative positions in the
heading frame (reduced by PCA), plus the root height as it is (heading and position in the room carry no
appearance).
"""

from __future__ import annotations

import numpy as np

from gsavatar.data_schema import load_capture
from gsavatar.synth.render import pose_joint_positions
from gsavatar.utils.cli import run_reporting_errors
from gsavatar.utils.io import atomic_write_json, read_npz

HISTORY = 10
"""Poses in the history window of the ``history`` regressor (the paper's N_b)."""
ALPHAS = tuple(10.0**k for k in range(-3, 8))
"""Ridge regularisations tried by :func:`ridge_cv` (features standardised; wide enough that CV never picks an end)."""
COMPONENTS: tuple[int | None, ...] = (12, 24, 48, None)
"""PCA components of the per-frame features tried by cross-validation (None: every feature, standardised)."""


def pose_features(pose: np.ndarray, root_translation: np.ndarray, joints: np.ndarray | None = None) -> np.ndarray:
    """Per-frame regressor inputs: pose parameters, the joints' positions relative to the first joint (the root)
    in its heading frame (yaw about +Y removed) when given, and last the root height (kept out of the PCA).

    pose [F, P], root_translation [F, 3], joints [F, J, 3] world -> [F, P (+ 3 J) + 1]
    """
    parts = [np.asarray(pose, np.float64)]
    if joints is not None:
        j = np.asarray(joints, np.float64)
        rel = j - j[:, :1]
        fwd = rel[:, min(1, j.shape[1] - 1)]  # root -> its first child (a hip): the heading
        yaw = np.arctan2(fwd[:, 0], fwd[:, 2])
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        x, z = rel[..., 0], rel[..., 2]
        parts.append(np.stack([c * x - s * z, rel[..., 1], s * x + c * z], -1).reshape(len(j), -1))
    parts.append(np.asarray(root_translation, np.float64)[:, 1:2])
    return np.concatenate(parts, 1)


def stack_history(x: np.ndarray, history: int) -> np.ndarray:
    """Frames ``t-history+1..t`` of every row, oldest first, clamped at row 0. [F, D] -> [F, history * D]"""
    idx = np.maximum(np.arange(len(x))[:, None] - np.arange(history - 1, -1, -1)[None], 0)
    return x[idx].reshape(len(x), -1)


def history_features(x: np.ndarray, history: int) -> np.ndarray:
    """Frame ``t``'s features, then the changes ``x_{t-k} - x_{t-k-1}`` for ``k = 0..history-2``.

    The same information as :func:`stack_history` (an invertible linear map of it). [F, D] -> [F, history * D]
    """
    s = stack_history(x, history).reshape(len(x), history, -1)  # oldest first
    d = (s[:, 1:] - s[:, :-1])[:, ::-1]  # newest change first
    return np.concatenate([s[:, -1], d.reshape(len(x), -1)], 1)


def ridge_fit(X: np.ndarray, Y: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ridge regression of ``Y`` on ``X`` standardised per column, with an unpenalised bias (``X`` and ``Y`` are
    centred; constant columns get unit scale). ``alpha`` is the absolute penalty on the standardised weights.
    [n, D], [n, E] -> the model for :func:`ridge_predict`"""
    mu, sd = X.mean(0), X.std(0)
    sd = np.where(sd > 1e-9, sd, 1.0)
    Z = (X - mu) / sd
    ym = Y.mean(0)
    n, D = Z.shape
    if D > n:  # the same solution in its dual form: (Z^T Z + a I)^-1 Z^T = Z^T (Z Z^T + a I)^-1
        W = Z.T @ np.linalg.solve(Z @ Z.T + alpha * np.eye(n), Y - ym)
    else:
        W = np.linalg.solve(Z.T @ Z + alpha * np.eye(D), Z.T @ (Y - ym))
    return mu, sd, W, ym


def ridge_predict(model, X: np.ndarray) -> np.ndarray:
    """Predictions of a :func:`ridge_fit` model. [m, D] -> [m, E]"""
    mu, sd, W, ym = model
    return ((X - mu) / sd) @ W + ym


def pooled_r2(pred: np.ndarray, target: np.ndarray) -> float:
    """``1 - sum SSE / sum SST`` over all columns (SST around each column's mean). [n, E] x2 -> float"""
    sst = float(((target - target.mean(0)) ** 2).sum())
    sse = float(((pred - target) ** 2).sum())
    return 1.0 - sse / sst if sst > 1e-12 else float("nan")


def ridge_cv(X: np.ndarray, Y: np.ndarray, folds: int = 5, alphas: tuple[float, ...] = ALPHAS) -> float:
    """Ridge regularisation (one of ``alphas``) with the lowest squared error over ``folds`` contiguous blocks of
    rows."""
    return ridge_cv_error(X, Y, folds, alphas)[0]


def ridge_cv_error(
    X: np.ndarray, Y: np.ndarray, folds: int = 5, alphas: tuple[float, ...] = ALPHAS
) -> tuple[float, float]:
    """:func:`ridge_cv`'s choice and its summed squared validation error. -> (alpha, error)"""
    n = len(X)
    edges = np.linspace(0, n, min(folds, n) + 1).astype(int)
    best, best_err = alphas[0], np.inf
    for a in alphas:
        err = 0.0
        for k in range(len(edges) - 1):
            va = np.zeros(n, bool)
            va[edges[k] : edges[k + 1]] = True
            if va.all() or not va.any():
                continue
            m = ridge_fit(X[~va], Y[~va], a)
            err += float(((ridge_predict(m, X[va]) - Y[va]) ** 2).sum())
        if err < best_err:
            best, best_err = a, err
    return best, best_err


MIN_TRAIN_CROSSINGS = 6
"""Fewer crossings of a state's training mean than this in the training frames: too few events to learn its cause."""


def mean_crossings(states: np.ndarray, mean: np.ndarray) -> list[int]:
    """How often each state crosses ``mean`` (a hysteresis: its flips; a spring: its swings).

    states [F, E], mean [E] -> [E] counts (a frame exactly at the mean continues the previous side)."""
    side = np.sign(np.asarray(states, np.float64) - np.asarray(mean, np.float64))
    out = []
    for e in range(side.shape[1]):
        s = side[:, e][side[:, e] != 0]
        out.append(int((s[1:] != s[:-1]).sum()))
    return out


def few_event_states(fairness: dict, names: list[str]) -> list[str]:
    """Warnings for states that cross their training mean fewer than :data:`MIN_TRAIN_CROSSINGS` times in the
    training frames (``fairness`` from :func:`predictability`)."""
    counts = fairness.get("crossings", {}).get("train", [])
    return [
        f"state {n!r} crosses its training mean only {c} times in the training frames: too few events for a "
        f"predictor to learn what causes it"
        for n, c in zip(names, counts)
        if c < MIN_TRAIN_CROSSINGS
    ]


def reduce_features(x: np.ndarray, train: np.ndarray, components: int | None = 12, raw_columns: int = 0) -> np.ndarray:
    """Per-frame features standardised on the ``train`` rows, all but the last ``raw_columns`` reduced to their first
    ``components`` PCA components (of the training rows; None: all of them, i.e. the standardised features
    rotated): keeps the history regressor small. [F, D] -> [F, <= c + r]"""
    x = np.asarray(x, np.float64)
    mu, sd = x[train].mean(0), x[train].std(0)
    z = (x - mu) / np.where(sd > 1e-9, sd, 1.0)
    keep = x.shape[1] - raw_columns
    _, _, vt = np.linalg.svd(z[train][:, :keep], full_matrices=False)
    c = vt.shape[0] if components is None else min(components, vt.shape[0])
    return np.concatenate([z[:, :keep] @ vt[:c].T, z[:, keep:]], 1)


def standardise_states(states: np.ndarray, train: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """States scaled to zero mean and unit std on the ``train`` rows. [F, E] -> ([F, E], training mean [E])"""
    y = np.asarray(states, np.float64).reshape(len(states), -1)
    ym, ys = y[train].mean(0), y[train].std(0)
    return (y - ym) / np.where(ys > 1e-9, ys, 1.0), ym


def ridge_r2(
    X: np.ndarray | list[np.ndarray],
    y: np.ndarray,
    train: np.ndarray,
    test: np.ndarray,
    alphas: tuple[float, ...] = ALPHAS,
) -> tuple[float, list[float], list[float], list[int]]:
    """Each state's ridge (its own regularisation by :func:`ridge_cv`) fit on the ``train`` rows, predictions clipped
    to the state's training range, scored on the ``test`` rows. X [F, D] (or a list of candidate feature matrices,
    one chosen per state by the same cross-validation), y [F, E]
    -> (pooled R^2, per-state R^2 [E], chosen alphas [E], chosen candidate indices [E])"""
    Xs = X if isinstance(X, list) else [X]
    pred = np.empty((len(test), y.shape[1]))
    chosen, which = [], []
    for e in range(y.shape[1]):
        cv = [ridge_cv_error(Xc[train], y[train][:, [e]], alphas=alphas) for Xc in Xs]
        i = int(np.argmin([err for _, err in cv]))
        chosen.append(cv[i][0])
        which.append(i)
        fit = ridge_fit(Xs[i][train], y[train][:, [e]], chosen[-1])
        # Clipped to the training range: a state never leaves it, and novel test poses must not extrapolate.
        pred[:, e] = np.clip(ridge_predict(fit, Xs[i][test])[:, 0], y[train][:, e].min(), y[train][:, e].max())
    per_state = [pooled_r2(pred[:, [e]], y[test][:, [e]]) for e in range(y.shape[1])]
    return pooled_r2(pred, y[test]), per_state, chosen, which


def predictability(
    features: np.ndarray,
    states: np.ndarray,
    train: np.ndarray,
    test: np.ndarray,
    history: int = HISTORY,
    components: int | None | tuple[int | None, ...] = COMPONENTS,
    raw_columns: int = 0,
) -> dict:
    """R^2 on ``test`` rows of the pose-only and the history regressor fit on ``train`` rows.

    features [F, D] per-frame inputs (the last ``raw_columns`` are kept as they are, the others reduced to
    ``components`` PCA components; a tuple: each state and regressor picks one by cross-validation), states [F, E]
    targets, train/test frame indices.
    -> {"pose_only", "history", "per_state": {"pose_only": [E], "history": [E]},
        "crossings": {"train": [E], "test": [E]} (:func:`mean_crossings` of the training mean), ...}
    """
    train, test = np.asarray(train, np.int64), np.asarray(test, np.int64)
    if len(train) < 4 or len(test) < 2:
        raise ValueError(f"need >= 4 train and >= 2 test frames, got {len(train)} and {len(test)}")
    cands = tuple(components) if isinstance(components, tuple) else (components,)
    zs = [reduce_features(features, train, c, raw_columns) for c in cands]
    y, ym = standardise_states(states, train)
    out: dict = {"per_state": {}}
    for name, Xs in (("pose_only", zs), ("history", [history_features(z, history) for z in zs])):
        out[name], out["per_state"][name], out[f"{name}_alpha"], which = ridge_r2(Xs, y, train, test)
        out[f"{name}_components"] = [zs[i].shape[1] - raw_columns for i in which]
    raw = np.asarray(states, np.float64).reshape(len(zs[0]), -1)
    out["crossings"] = {"train": mean_crossings(raw[train], ym), "test": mean_crossings(raw[test], ym)}
    out.update(
        {
            "metric": "R^2 on test frames, pooled over standardised states",
            "history_frames": history,
            "regressor": f"ridge on {'/'.join(str(z.shape[1] - raw_columns) for z in zs)} pose PCA components "
            f"(+ {raw_columns} raw); history: frame t's and the frame-to-frame changes; columns standardised, "
            "components and alpha per state by 5-fold contiguous CV, clipped to the training range",
        }
    )
    return out


def _json_ready(v):
    """NaN / inf floats (a state constant on the test frames) as None, recursively."""
    if isinstance(v, dict):
        return {k: _json_ready(w) for k, w in v.items()}
    if isinstance(v, list):
        return [_json_ready(w) for w in v]
    return None if isinstance(v, float) and not np.isfinite(v) else v


def history_fairness(
    motion,
    states: np.ndarray,
    train: np.ndarray,
    test: np.ndarray,
    history: int = HISTORY,
    joints: np.ndarray | None = None,
) -> dict:
    """:func:`predictability` of the appearance ``states`` [F, E] from a capture's ``motion`` and its posed
    ``joints`` [F, J, 3] (JSON-ready)."""
    features = pose_features(motion.pose, motion.root_translation, joints)
    return _json_ready(predictability(features, states, train, test, history, raw_columns=1))


def capture_inputs(capture) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the fairness check of a written synthetic capture reads: per-frame :func:`pose_features` (root height
    last), the true states ``gt/motion_states.npz`` levels, the train and test frames.
    -> (features [F, D], levels [F, E], train [n], test [m])"""
    from pathlib import Path

    capture = Path(capture)
    cap = load_capture(capture)
    levels = read_npz(capture / "gt" / "motion_states.npz", keys=("levels",))["levels"]
    m = cap.motion
    joints = pose_joint_positions(cap.rig, m.pose, m.root_rotation, m.root_translation)
    features = pose_features(m.pose, m.root_translation, joints)
    return features, levels, np.asarray(cap.splits["train"].frames), np.asarray(cap.splits["test"].frames)


def capture_fairness(capture) -> dict:
    """The fairness check (:func:`predictability`, JSON-ready) of a written synthetic capture."""
    features, levels, train, test = capture_inputs(capture)
    return _json_ready(predictability(features, levels, train, test, raw_columns=1))


def main(argv: list[str] | None = None) -> int:
    """``python -m gsavatar.synth.fairness CAPTURE [--write]``: print (and rewrite gt/fairness.json)."""
    import argparse
    import json
    from pathlib import Path

    ap = argparse.ArgumentParser(
        description="How well pose alone / the pose history predict a synthetic "
        "capture's history-caused appearance states (R^2 on test frames)."
    )
    ap.add_argument("capture", type=Path)
    ap.add_argument("--write", action="store_true", help="rewrite CAPTURE/gt/fairness.json")
    a = ap.parse_args(argv)

    def run() -> None:
        res = capture_fairness(a.capture)
        print(json.dumps({k: res[k] for k in ("pose_only", "history", "per_state")}))
        if a.write:
            atomic_write_json(a.capture / "gt" / "fairness.json", res)

    return run_reporting_errors(run)


if __name__ == "__main__":
    raise SystemExit(main())
