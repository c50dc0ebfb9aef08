"""How much could a learned model add to ``srp_phat``? The headroom in its per-frame candidates.

``srp_phat`` fits ``frame_candidates`` points to every 85 ms frame and detects a frame when the best
one's response passes the null threshold. On test recordings this script reports, beside
``srp_phat`` itself:

- **oracle**: each window takes its candidate nearest the ground truth and counts as detected when it
  lies within ``radius``; then ``srp_phat``'s own confirmation, hold and fallback: what a perfect
  re-scoring of the candidates would reach (it finds no point the search did not propose).
- **learned scorer**: a gradient-boosted classifier (scikit-learn), trained on the training recordings'
  labels (``pseudo``: the LiDAR teacher's, as a student with alpha = 1; ``gt``: ground truth), that
  tells whether a candidate lies within ``radius`` of the label. Its features are the candidate's responses only: on its
  own frame, over every frame of the window (mean, median, upper quartile, maximum, share above the
  threshold), how many frames' best points lie within 2 m and 5 m of it, its rank in its frame, and the
  window's best own and mean responses; never its coordinates (the pseudo-labels are biased to near
  range). ``scorer > tau``: a frame is detected when its most probable candidate passes ``tau``;
  ``gated tau``: ``srp_phat``'s rule on the candidates the scorer keeps (probability above ``tau``).
  Every tau given is reported; none is chosen on the test recordings.

Every variant goes through ``srp_phat``'s window median, confirmation, hold and fallback, with the
settings of ``configs/model/srp_phat.yaml`` (``--config``, ``--net-kwargs``). The test recordings'
ground truth is used only to score.

Run: ``python -m benchmarks.studies.phase_headroom --train DIR [DIR ...] --test DIR [DIR ...]``.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import torch
import yaml
from sklearn.ensemble import HistGradientBoostingClassifier

from benchmarks.studies.common import recordings_module
from zoo.nets.phase.search import best_candidates
from zoo.nets.phase.srp_phat import SRPPhat
from zoo.registry import get_model

#: candidate features, in the order :func:`candidate_features` stacks them
FEATURES = ("own", "mean", "median", "upper_quartile", "max", "share_detected", "near_2m", "near_5m", "rank",
            "window_best_own", "window_best_mean")
#: the model config whose ``net_kwargs`` build the net (``--config``)
CONFIG = Path(__file__).resolve().parents[2] / "configs" / "model" / "srp_phat.yaml"


def config_net_kwargs(config: Path) -> dict:
    """The ``model.init_args.net_kwargs`` of a model config (YAML); ValueError naming the file if it has none."""
    try:
        kwargs = yaml.safe_load(config.read_text())["model"]["init_args"]["net_kwargs"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as error:
        raise ValueError(f"{config}: expected a model config with model.init_args.net_kwargs ({error})") from None
    return dict(kwargs)


def candidate_features(net: SRPPhat, correlation: torch.Tensor, points: torch.Tensor, scores: torch.Tensor,
                       mics: torch.Tensor) -> torch.Tensor:
    """Features (B x F*K x len(FEATURES)) of windows' candidates ``points`` (B x F x K x 3) with their own
    frames' responses ``scores`` (B x F x K), from correlations B x F x pairs x lags; responses are in units
    of the detection threshold."""
    b, f, k, _ = points.shape
    threshold = net.threshold(mics)
    flat = points.reshape(b, 1, f * k, 3).expand(b, f, f * k, 3).reshape(b * f, f * k, 3)
    frames = correlation.float().reshape(b * f, *correlation.shape[2:])
    across = (net.steering.response(frames, flat, mics).reshape(b, f, f * k).transpose(1, 2) / threshold).float()
    own = scores.reshape(b, f * k) / threshold
    best = best_candidates(points, scores)[0]  # B x F x 3
    distance = torch.cdist(points.reshape(b, f * k, 3), best)  # B x FK x F
    rank = scores.argsort(dim=2, descending=True).argsort(dim=2).reshape(b, f * k).float()
    mean = across.mean(dim=2)
    columns = [own, mean, across.median(dim=2).values, across.quantile(0.75, dim=2), across.amax(dim=2),
               (across > 1).float().mean(dim=2), (distance < 2).float().mean(dim=2),
               (distance < 5).float().mean(dim=2), rank,
               own.amax(dim=1, keepdim=True).expand(-1, f * k), mean.amax(dim=1, keepdim=True).expand(-1, f * k)]
    return torch.stack(columns, dim=2)


def collect(net: SRPPhat, data: list[Path], cache: Path | None, label_rate: float | None = None
            ) -> dict[str, np.ndarray]:
    """Every window's candidates, their responses and features, with its labels, time and sequence."""
    module = recordings_module(data, net.inputs["audio_phase"], cache, label_rate=label_rate)
    net.set_bounds(module.hparams.bev_bounds)
    keep: dict[str, list[np.ndarray]] = {}
    for batch in module.test_dataloader()[0]:
        phase = batch["audio_phase"]
        with torch.no_grad():
            for mics, rows in net.geometry_groups(phase, batch["mic_positions"]):
                correlation = phase[rows].permute(0, 2, 1, 3).float()
                points, scores = net.search.fitted_candidates(correlation, mics)
                found = {"points": points, "scores": scores / net.threshold(mics),
                         "features": candidate_features(net, correlation, points, scores, mics)}
                found.update({name: batch[name][rows] for name in ("gt", "gt_valid", "pseudo", "pseudo_valid",
                                                                   "time", "sequence")})
                for name, value in found.items():
                    keep.setdefault(name, []).append(value.numpy())
    return {name: np.concatenate(values) for name, values in keep.items()}


def track(net: SRPPhat, arrays: dict[str, np.ndarray], frame_points: np.ndarray, hit: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Positions (B x 3) and counted detections (B) of windows whose frames give ``frame_points``
    (B x F x 3), detected where ``hit`` (B x F): ``srp_phat``'s median, confirmation, hold and fallback."""
    hit_t = torch.from_numpy(hit)
    positions = net.window_positions(torch.from_numpy(frame_points).float(), hit_t)
    order = np.lexsort((arrays["time"], arrays["sequence"]))
    out, detected = net.hold_or_fallback(positions[order], hit_t[order].any(dim=1),
                                         torch.from_numpy(arrays["sequence"][order]),
                                         torch.from_numpy(arrays["time"][order]))
    back = np.argsort(order)
    return out.numpy()[back], detected.numpy()[back]


def best_of(points: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~zoo.nets.phase.search.best_candidates` on arrays: per frame, the candidate of highest ``values``
    and that value."""
    best, value = best_candidates(torch.from_numpy(points), torch.from_numpy(values))
    return best.numpy(), value.numpy()


def oracle(arrays: dict[str, np.ndarray], radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Per window, the candidate nearest the ground truth (B x 3) and whether it lies within ``radius`` (B),
    repeated over the window's frames (B x F x 3, B x F) for :func:`track`."""
    b, f, k, _ = arrays["points"].shape
    flat = arrays["points"].reshape(b, f * k, 3)
    distance = np.linalg.norm(flat - arrays["gt"][:, None], axis=2)
    nearest = flat[np.arange(b), distance.argmin(axis=1)]
    return np.repeat(nearest[:, None], f, axis=1), np.repeat((distance.min(axis=1) < radius)[:, None], f, axis=1)


def train_scorer(arrays: dict[str, np.ndarray], labels: str, radius: float) -> HistGradientBoostingClassifier:
    """The classifier of 'candidate within ``radius`` of the label' on the labelled windows' candidates."""
    valid = arrays[f"{labels}_valid"]
    near = np.linalg.norm(arrays["points"] - arrays[labels][:, None, None], axis=3) < radius
    features, target = arrays["features"][valid].reshape(-1, len(FEATURES)), near[valid].reshape(-1)
    if target.all() or not target.any():
        raise ValueError(f"phase_headroom: the training windows' {labels} labels leave "
                         f"{'no' if not target.any() else 'only'} candidates within {radius} m; "
                         "a scorer needs both kinds")
    return HistGradientBoostingClassifier(max_iter=100, max_depth=3, random_state=0).fit(features, target)


def headroom(net: SRPPhat, train: dict[str, np.ndarray], test: dict[str, np.ndarray],
             labels: tuple[str, ...] = ("pseudo", "gt"), radius: float = 2.0,
             taus: tuple[float, ...] = (0.1, 0.2, 0.3, 0.5, 0.7)) -> dict[str, dict[str, float]]:
    """E and detected share on the test windows with ground truth: srp_phat, the oracle and the scorer
    trained on each of ``labels``."""
    valid = test["gt_valid"]
    points, scores = test["points"], test["scores"]
    b, f, k, _ = points.shape

    def score(frame_points: np.ndarray, hit: np.ndarray) -> dict[str, float]:
        position, detected = track(net, test, frame_points, hit)
        error = np.linalg.norm(position - test["gt"], axis=1)[valid]
        return {"E": float(error.mean()), "detected": float(detected[valid].mean())}

    best, best_score = best_of(points, scores)
    rows = {"srp_phat": score(best, best_score > 1), "oracle": score(*oracle(test, radius))}
    for name in labels:
        scorer = train_scorer(train, name, radius)
        probability = scorer.predict_proba(test["features"].reshape(-1, len(FEATURES)))[:, 1].reshape(b, f, k)
        chosen, chosen_probability = best_of(points, probability)
        for tau in taus:
            rows[f"{name}: scorer > {tau:g}"] = score(chosen, chosen_probability > tau)
        for tau in taus:
            kept, kept_score = best_of(points, np.where(probability > tau, scores, 0.0))
            rows[f"{name}: gated {tau:g}"] = score(kept, kept_score > 1)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=Path, nargs="+", required=True, help="recordings the scorer learns from")
    parser.add_argument("--test", type=Path, nargs="+", required=True, help="held-out recordings it is scored on")
    parser.add_argument("--labels", choices=("pseudo", "gt"), nargs="+", default=["pseudo", "gt"],
                        help="the scorer's training labels: one scorer each")
    parser.add_argument("--train-label-rate", type=float, default=5.0, help="training windows per second")
    parser.add_argument("--radius", type=float, default=2.0, help="m: a candidate this near the label is right")
    parser.add_argument("--taus", type=float, nargs="+", default=[0.1, 0.2, 0.3, 0.5, 0.7])
    parser.add_argument("--config", type=Path, default=CONFIG, help="srp_phat model config whose net_kwargs to use")
    parser.add_argument("--net-kwargs", default="{}", help="srp_phat keyword arguments over the config's, as JSON")
    parser.add_argument("--cache", type=Path, help="feature cache folder (default $AAUTE_CACHE)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(args.threads)
    try:
        net_kwargs = json.loads(args.net_kwargs)
    except json.JSONDecodeError as error:
        parser.error(f"--net-kwargs must be a JSON object of srp_phat arguments: {error}")
    try:
        net_kwargs = {**config_net_kwargs(args.config), **net_kwargs}
    except ValueError as error:
        parser.error(str(error))
    net = get_model("srp_phat", **net_kwargs)
    train = collect(net, args.train, args.cache, args.train_label_rate)
    test = collect(net, args.test, args.cache)
    rows = headroom(net, train, test, tuple(args.labels), args.radius, tuple(args.taus))
    print(f"{'':>20s} {'E (m)':>8s} {'detected':>9s}   (radius {args.radius:g} m)")
    for name, row in rows.items():
        print(f"{name:>20s} {row['E']:8.2f} {row['detected']:9.2f}")


if __name__ == "__main__":
    main()
