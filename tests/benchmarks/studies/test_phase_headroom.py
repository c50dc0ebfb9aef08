"""The headroom of srp_phat's candidates: oracle choice, features, tracking, the scorer, and a run on recordings."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.studies.phase_headroom import FEATURES, candidate_features, headroom, main, oracle, track, train_scorer
from datamodules.simulate.microphones import distributed4
from zoo.registry import get_model


@pytest.fixture(scope="module")
def net():
    torch.set_num_threads(1)
    return get_model("srp_phat", null_windows=20, input_recipes={"audio_phase": "gcc_phat_2s_static"})


def test_oracle_takes_the_candidate_nearest_the_truth_and_detects_within_the_radius():
    points = np.zeros((2, 2, 2, 3))
    points[0, 1, 0] = [3.0, 10.0, 5.0]  # 0.5 m from window 0's truth
    points[1, :, :] = [20.0, 20.0, 20.0]  # window 1: every candidate far
    arrays = {"points": points, "gt": np.array([[3.0, 10.5, 5.0], [0.0, 10.0, 5.0]])}
    nearest, hit = oracle(arrays, radius=2.0)
    np.testing.assert_allclose(nearest[0], [[3.0, 10.0, 5.0]] * 2)
    assert hit[0].all() and not hit[1].any()
    assert oracle(arrays, radius=0.4)[1][0].sum() == 0


def test_candidate_features_count_support_rank_and_responses_in_threshold_units(net):
    mics = torch.as_tensor(distributed4(), dtype=torch.float64)
    rng = torch.Generator().manual_seed(0)
    correlation = torch.rand(1, 5, 6, net.recipe.num_lags(), generator=rng) * 0.1
    points = torch.tensor([10.0, 15.0, 8.0]) + torch.rand(1, 5, 2, 3, generator=rng) * 20
    points[0, :, 0] = torch.tensor([5.0, 12.0, 6.0])  # every frame's first candidate: the same point
    scores = torch.tensor([[[0.9, 0.1], [0.8, 0.2], [0.7, 0.3], [0.6, 0.4], [0.55, 0.45]]])
    features = candidate_features(net, correlation, points, scores, mics)
    assert features.shape == (1, 10, len(FEATURES))
    column = {name: features[0, :, i] for i, name in enumerate(FEATURES)}
    threshold = net.threshold(mics)
    torch.testing.assert_close(column["own"], (scores.reshape(-1) / threshold).float())
    assert bool((column["near_2m"][0::2] == 1).all())  # the best point of every frame
    assert column["rank"].tolist() == [0.0, 1.0] * 5
    response = net.steering.response(correlation[0].float(), points[0, :1, :1].reshape(1, 1, 3).expand(5, 1, 3), mics)
    torch.testing.assert_close(column["mean"][0], (response.mean() / threshold).float())


def test_track_runs_srp_phats_hold_on_windows_in_any_order(net):
    frames = np.array([[[5.0, 12.0, 6.0]] * 2, [[0.0, 0.0, 0.0]] * 2, [[5.0, 13.0, 6.0]] * 2])
    hit = np.array([[True, True], [False, False], [True, False]])
    arrays = {"time": np.array([1.0, 1.2, 1.1]), "sequence": np.zeros(3, dtype=np.int64)}
    position, detected = track(net, arrays, frames, hit)
    assert detected.tolist() == [True, False, True]
    np.testing.assert_allclose(position[1], [5.0, 13.0, 6.0])  # window at 1.2 s holds the one at 1.1 s


def test_scorer_needs_candidates_near_and_far_from_the_labels():
    arrays = {"points": np.zeros((3, 1, 2, 3)), "pseudo": np.zeros((3, 3)), "pseudo_valid": np.ones(3, dtype=bool),
              "features": np.zeros((3, 2, len(FEATURES)))}
    with pytest.raises(ValueError, match="both kinds"):
        train_scorer(arrays, "pseudo", 2.0)


def test_scorer_learns_which_candidates_are_right_from_their_features(net):
    """Candidates whose 'own' feature marks the source: the scorer finds them where srp_phat's rule fails."""
    rng = np.random.default_rng(1)
    n, f, k = 60, 4, 3

    def windows(seed_offset: float) -> dict[str, np.ndarray]:
        truth = np.stack([np.full(n, 3.0), np.linspace(8.0, 20.0, n) + seed_offset, np.full(n, 10.0)], axis=1)
        points = truth[:, None, None] + rng.normal(0, 8.0, (n, f, k, 3))
        points[:, :, 0] = truth[:, None] + rng.normal(0, 0.2, (n, f, 3))
        features = rng.normal(0, 1, (n, f * k, len(FEATURES)))
        features[:, 0::k, 0] += 4.0  # the right candidates stand out in one feature
        scores = rng.uniform(0.0, 0.9, (n, f, k))  # srp_phat's responses never pass the threshold
        return {"points": points, "scores": scores, "features": features, "gt": truth, "pseudo": truth,
                "gt_valid": np.ones(n, dtype=bool), "pseudo_valid": np.ones(n, dtype=bool),
                "time": np.arange(n) / 10.0, "sequence": np.zeros(n, dtype=np.int64)}

    rows = headroom(net, windows(0.0), windows(0.5), labels=("pseudo",), taus=(0.5,))
    assert rows["srp_phat"]["detected"] == 0.0
    assert rows["oracle"]["E"] < 0.5
    assert rows["pseudo: scorer > 0.5"]["E"] < 1.0 and rows["pseudo: scorer > 0.5"]["detected"] > 0.9
    assert rows["pseudo: gated 0.5"]["detected"] == 0.0  # gating cannot add detections


def test_headroom_runs_on_labelled_recordings(labelled_dir, feature_cache, capsys):
    recordings = sorted(labelled_dir.glob("*.mcap"))
    main(["--train", str(recordings[1]), "--test", str(recordings[2]), "--labels", "pseudo", "--taus", "0.5",
          "--net-kwargs", '{"null_windows": 20}', "--cache", str(feature_cache)])
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines[1:3]] == ["srp_phat", "oracle"]
    assert len(lines) == 5 and all(np.isfinite(float(line.split()[-2])) for line in lines[1:])
