"""Audio2ExpressionNet, vertex-space loss, closed-form person maps, training with resume."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from nvp.app.train_audio2exp import Audio2ExpTrainConfig, evaluate_person, train
from nvp.audio2exp import (
    Audio2ExpConfig,
    Audio2ExpressionNet,
    ExpressionFilter,
    PerFrameNet,
    VertexMetric,
    load_net,
    network_outputs,
    save_net,
    solve_person_map,
)
from nvp.person import VideoSample
from nvp.tracked import TrackedSequence

CFG = Audio2ExpConfig(feature_dim=12)


def test_per_frame_net_shapes_and_range():
    net = PerFrameNet(CFG)
    out = net(torch.randn(5, 16, 12))
    assert out.shape == (5, 32)
    assert out.abs().max() <= 1
    with pytest.raises(ValueError, match="feature windows"):
        net(torch.randn(16, 12))


def test_filter_weights_are_a_convex_combination():
    filt = ExpressionFilter(CFG)
    preds = torch.randn(4, 8, 32)
    out, w = filt(preds)
    assert w.shape == (4, 8)
    torch.testing.assert_close(w.sum(-1), torch.ones(4))
    # identical predictions pass through unchanged
    same = torch.randn(4, 1, 32).expand(4, 8, 32)
    torch.testing.assert_close(filt(same)[0], same[:, 0])


def test_sequence_is_aligned_and_batch_independent():
    net = Audio2ExpressionNet(CFG).eval()
    w = torch.randn(30, 16, 12)
    with torch.no_grad():
        a = net.sequence(w)
        b = net.sequence(w, batch=7)
        raw = net.sequence(w, use_filter=False)
    assert a.shape == raw.shape == (30, 32)
    torch.testing.assert_close(a, b)


def test_parameter_count_is_small():
    net = Audio2ExpressionNet(Audio2ExpConfig())
    assert sum(p.numel() for p in net.parameters()) < 200_000


def test_vertex_metric_matches_explicit_vertices(face_model):
    metric = VertexMetric(face_model.exp_basis, face_model.vertex_regions["mouth"], 10.0)
    d = torch.randn(3, face_model.num_exp)
    verts = np.einsum("tk,kvc->tvc", d.numpy(), face_model.exp_basis)
    w = np.where(face_model.vertex_regions["mouth"], 10.0, 1.0)
    explicit = (w * (verts**2).sum(-1)).sum(-1) / w.sum()
    np.testing.assert_allclose(metric.sq(d).numpy(), explicit, rtol=1e-4)


def test_temporal_term_penalises_jitter_not_offsets(face_model):
    metric = VertexMetric(face_model.exp_basis, face_model.vertex_regions["mouth"])
    target = torch.zeros(2, 3, face_model.num_exp)
    offset = torch.ones(2, 3, face_model.num_exp) * 0.1
    jitter = offset.clone()
    jitter[:, 1] *= -1
    assert float(metric.loss(offset, target)) == pytest.approx(
        float(metric.loss(offset, target, 0.0)), abs=1e-4
    )
    assert metric.loss(jitter, target) > 5 * metric.loss(offset, target)


def test_person_map_recovers_a_known_linear_map():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 32))
    m = rng.normal(size=(20, 32))
    b = rng.normal(size=20)
    d = a @ m.T + b + rng.normal(0, 0.01, (500, 20))
    pm = solve_person_map(a, d, ridge=1e-3)
    np.testing.assert_allclose(pm.matrix, m, atol=0.01)
    np.testing.assert_allclose(pm.bias, b, atol=0.01)
    with pytest.raises(ValueError, match="frames"):
        solve_person_map(a[:10], d[:11])


def fake_sample(face_model, name, seed, frames=120, dim=12):
    """Feature windows whose first channels drive the expression linearly (a learnable toy 'speech')."""
    rng = np.random.default_rng(seed)
    signal = np.cumsum(rng.normal(size=(frames + 16, dim)), 0) * 0.2
    windows = np.stack([signal[t : t + 16] for t in range(frames)]).astype(np.float32)
    mix = rng.normal(size=(face_model.num_exp, dim)) * 0.3
    expr = (np.tanh(windows[:, 8]) @ mix.T).astype(np.float32)
    eye = np.tile(np.eye(3, dtype=np.float32), (frames, 1, 1))
    lm = np.zeros((frames, 468, 2), np.float32)
    lm[:, face_model.landmark_groups["left_eye"], 0] = 60
    lm[:, face_model.landmark_groups["right_eye"], 0] = 0
    seq = TrackedSequence(
        fps=25.0,
        width=256,
        height=256,
        focal=1000.0,
        center=np.array([128, 128], np.float32),
        identity=np.zeros(face_model.num_id, np.float32),
        rotation=eye,
        translation=np.tile(np.array([0, 0, 60], np.float32), (frames, 1)),
        expression=expr,
        landmarks=lm,
        valid=np.ones(frames, bool),
        fit_error=np.zeros(frames, np.float32),
        face_model_sha256=face_model.sha256,
    )
    return VideoSample(name=name, windows=windows, tracked=seq)


def test_mean_expression_baseline_and_perfect_prediction(face_model):
    s = fake_sample(face_model, "a", 0)
    base = evaluate_person(s, face_model, None)
    assert base["mouth_error_iod"] > 0
    # an "audio-expression" equal to the expression itself is mapped perfectly
    perfect = evaluate_person(s, face_model, s.expression[:, :32].copy(), ridge=1e-6)
    assert perfect["mouth_error_iod"] < base["mouth_error_iod"]


@pytest.fixture
def one_thread():
    """A toy network runs fastest on one thread, and another process cannot stall it at OpenMP barriers."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_training_learns_and_resumes_exactly(face_model, tmp_path, one_thread):
    train_set = [fake_sample(face_model, f"v{i}", i) for i in range(3)]
    val_set = [fake_sample(face_model, "val", 9)]
    cfg = Audio2ExpTrainConfig(steps=100, batch=16, lr=3e-3, val_every=50, net=CFG)
    straight = train(train_set, val_set, face_model, cfg, tmp_path / "a", progress=False)
    # Learning, against the same network not learning: batches depend only on (seed, step), so a run with
    # both learning rates 0 sees the very same batches, and its loss is what their composition alone gives.
    # (Unpaired, the logged loss, a mean over the last 50 steps at batch 16, is too noisy to say much: with
    # nothing learned, a 40-step run's second half measured 0.79-1.15 of its first on ten draws of this toy.)
    frozen = dataclasses.replace(cfg, lr=0.0, map_lr=0.0)
    still = train(train_set, val_set, face_model, frozen, tmp_path / "frozen", progress=False)
    ratio = straight["log"][-1]["train_loss"] / still["log"][-1]["train_loss"]
    # Without learning the ratio is 1 by construction. Steps 51-100 cost 0.47 of the still network's loss
    # on this toy, 0.47-0.80 on ten draws of its data and seed, so 0.85 holds for any of them (and far
    # beyond float rounding from CPU to CPU, ~1e-2 by step 100), while a network that learns less fails.
    assert ratio < 0.85, f"steps 51-100 cost {ratio:.2f} of the loss of the same network not learning"
    first = train(
        train_set, val_set, face_model, dataclasses.replace(cfg, steps=50), tmp_path / "b", progress=False
    )
    resumed = train(train_set, val_set, face_model, cfg, tmp_path / "b", progress=False)
    assert [r["step"] for r in resumed["log"]] == [50, 100]
    assert resumed["log"][0] == first["log"][0]  # the first half was not redone
    # same batches and optimiser state: equal up to float rounding amplified over 50 steps
    assert resumed["log"][-1]["train_loss"] == pytest.approx(straight["log"][-1]["train_loss"], rel=1e-2)
    assert torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)["step"] == 100
    net, manifest = load_net(tmp_path / "a" / "best.json")
    assert manifest["feature_kind"] == "phonemes" and net.cfg.feature_dim == 12


def test_save_load_round_trip(tmp_path):
    net = Audio2ExpressionNet(CFG)
    save_net(net, tmp_path / "m", {"note": 1})
    back, m = load_net(tmp_path / "m.json")
    x = torch.randn(20, 16, 12)
    with torch.no_grad():
        torch.testing.assert_close(back.sequence(x), net.eval().sequence(x))
    assert m["note"] == 1


def test_closure_head_outputs_and_round_trip(tmp_path):
    cfg = dataclasses.replace(CFG, closure_head=True)
    net = Audio2ExpressionNet(cfg).eval()
    x = torch.randn(20, 16, 12)
    raw, logits = net.frame_outputs(x)
    assert raw.shape == (20, 32) and logits.shape == (20,)
    torch.testing.assert_close(raw, net.per_frame(x))  # the head changes nothing of the expressions
    p = network_outputs(net, [x.numpy()])[1]
    assert p.shape == (20,) and np.all((p > 0) & (p < 1))
    save_net(net, tmp_path / "m", {})
    back, _ = load_net(tmp_path / "m.json")
    np.testing.assert_allclose(network_outputs(back, [x.numpy()])[1], p, rtol=1e-6)
    assert network_outputs(Audio2ExpressionNet(CFG), [x.numpy()])[1] is None


def test_closure_head_learns_when_the_lips_close(face_model, tmp_path):
    from nvp.app.train_audio2exp import closed_frames

    train_set = [fake_sample(face_model, f"v{i}", i, frames=200) for i in range(3)]
    cfg = Audio2ExpTrainConfig(steps=300, batch=32, lr=3e-3, val_every=300, closure_weight=1.0, net=CFG)
    train(train_set, train_set[:1], face_model, cfg, tmp_path / "a", progress=False)
    net, _ = load_net(tmp_path / "a" / "best.json")
    assert net.cfg.closure_head
    labels = np.concatenate([closed_frames(s, face_model) for s in train_set]).astype(bool)
    p = np.concatenate([network_outputs(net, [s.windows])[1] for s in train_set])
    assert 0.05 < labels.mean() < 0.5
    # the closed frames are told apart from the open ones (area under the ROC curve)
    auc = (p[labels][:, None] > p[~labels][None]).mean()
    assert auc > 0.8, auc


def test_two_processes_under_torchrun_follow_the_one_process_run(tmp_path, torchrun):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).parent / "ddp_train_toy.py"
    cmd = [sys.executable, script, tmp_path / "one"]
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    assert proc.returncode == 0, f"one: {proc.stderr[-1500:]}"
    torchrun(script, tmp_path / "two")
    runs = ("one", "two")
    logs = {k: json.loads((tmp_path / k / "log.json").read_text()) for k in runs}
    assert [r["step"] for r in logs["one"]] == [r["step"] for r in logs["two"]] == list(range(5, 21, 5))
    one = np.array([r["train_loss"] for r in logs["one"]])
    two = np.array([r["train_loss"] for r in logs["two"]])
    # same batches, each process half of each; the RMS loss is made from sums over both, so the loss and its
    # gradient are the one-process ones: the curves agree up to float rounding. Adam amplifies a rounding
    # difference about tenfold every 10 steps on this toy (measured with ATEN_CPU_CAPABILITY=default, whose
    # unvectorised sums round like no other CPU's: 7e-8 at step 10, 3e-6 at 20, 3e-4 at 60), so the run is
    # kept to 20 steps, where any CPU's rounding stays 30x below the tolerance and a wrong split is not
    np.testing.assert_allclose(two, one, rtol=1e-4)
    assert one[-1] < one[0]
    val = [np.array([r["mouth_error_iod"] for r in logs[k]]) for k in runs]
    np.testing.assert_allclose(val[1], val[0], rtol=1e-4)


def test_a_resumed_training_says_so_and_a_damaged_checkpoint_is_one_clear_error(
    face_model, tmp_path, one_thread, caplog
):
    import logging

    from nvp.errors import FormatError

    train_set = [fake_sample(face_model, f"v{i}", i) for i in range(2)]
    val_set = [fake_sample(face_model, "val", 9)]
    cfg = Audio2ExpTrainConfig(steps=2, batch=4, val_every=2, net=CFG)
    train(train_set, val_set, face_model, cfg, tmp_path / "a", progress=False)
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # visible without -v
        train(
            train_set, val_set, face_model, dataclasses.replace(cfg, steps=4), tmp_path / "a", progress=False
        )
    said = [r.getMessage() for r in caplog.records if "resuming" in r.getMessage()]
    assert len(said) == 1 and "at step 2 of 4" in said[0], said
    ckpt = tmp_path / "a" / "checkpoint.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:1000])  # cut short
    with pytest.raises(FormatError, match="damaged and cannot be read.*delete it to start training again"):
        train(
            train_set, val_set, face_model, dataclasses.replace(cfg, steps=6), tmp_path / "a", progress=False
        )
