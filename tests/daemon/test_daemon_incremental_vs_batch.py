# SPDX-License-Identifier: Apache-2.0
"""Incremental (streaming, as the daemon drives it) versus batch (paper mode) sigma^2_occ.

A synthetic sequence is replayed through the daemon's call schedule: ``depth_from_stereo`` ->
``integrate`` -> ``train_steps(daemon.train_steps_per_frame)`` per frame, then idle rounds of
``train_steps(daemon.idle_train_steps)`` until the model is ready. A second pipeline ingests the
same frames and runs the paper's batch fit (``fit_paper``: fresh model, Adam, 100 epochs). Both
predict sigma^2_occ (Algorithm 1) on the same query cloud. Agreement measure: Spearman rank
correlation of the two sigma^2_occ vectors (ranking is what Eq. 13 uses), reported together with
the same figure for two batch fits that differ only in their seed (the noise floor).
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from scipy.stats import spearmanr

from pugsd.config import core_of, load_config, load_config_dict
from pugsd.core.pipeline import PugsPipeline
from pugsd.daemon.app import Daemon
from pugsd.daemon.demo import SyntheticCamera
from tests.daemon.conftest import daemon_config_dict, wait_for
from tests.daemon.stereo_publisher import load_frames
from tests.daemon.test_daemon_inprocess import DaemonThread, RecordingNotifier


@pytest.mark.slow
def test_streaming_sigma2_agrees_with_batch(record_property: object) -> None:
    from pugsd.sim.sequence import make_sequence

    cfg = load_config(None, ["stereo.downsample=2"])
    d = cfg.daemon
    seq = make_sequence("mug", "partial", n_frames=8, width=320, height=240, seed=1)
    stream = PugsPipeline(core_of(cfg), seed=0)
    batch = PugsPipeline(core_of(cfg), seed=0)
    batch2 = PugsPipeline(core_of(cfg), seed=1)
    t0 = time.perf_counter()
    for f in seq.frames:
        depth = stream.depth_from_stereo(f)
        stream.integrate(depth)
        stream.train_steps(d.train_steps_per_frame)
        batch.integrate(depth)
        batch2.integrate(depth)
    rounds = 0
    while not stream.ready and rounds < 200:
        stream.train_steps(d.idle_train_steps)
        rounds += 1
    t_stream = time.perf_counter() - t0
    assert stream.ready, f"streaming model not ready after {rounds} idle rounds"
    t1 = time.perf_counter()
    batch.fit_paper()
    t_batch = time.perf_counter() - t1
    batch2.fit_paper()
    q = stream.query_cloud()
    _, s2_stream = stream.sigma2_occ(q)
    _, s2_batch = batch.sigma2_occ(q)
    _, s2_batch2 = batch2.sigma2_occ(q)
    rho = float(spearmanr(s2_stream, s2_batch).statistic)
    rho_floor = float(spearmanr(s2_batch2, s2_batch).statistic)
    rel = float(np.median(np.abs(s2_stream - s2_batch) / np.maximum(s2_batch, 1e-12)))
    msg = (
        f"incremental vs batch sigma2_occ on Q={len(q)} points: Spearman {rho:.3f} "
        f"(batch seed 0 vs seed 1: {rho_floor:.3f}); median relative difference {rel:.2f}; "
        f"streaming {stream.svgp.total_steps} steps in {t_stream:.1f} s incl. depth, "
        f"batch fit {t_batch:.1f} s"
    )
    print("\n" + msg)
    record_property("incremental_vs_batch", msg)  # type: ignore[operator]
    assert rho > 0.7, msg


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_daemon_streaming_sigma2_agrees_with_batch_on_the_same_points(
    port: int, client: zenoh.Session, sequence_npz: Path
) -> None:
    """The same comparison with the streaming model exactly as the daemon trained it: a sequence
    is replayed over loopback zenoh into an in-process daemon; once it has published grasps and
    trained on (idle rounds) to 150 streaming steps, the batch fit runs on a copy of the daemon's
    own point store. Measured: Spearman 0.59-0.70 after about 150 steps (see the assertion)."""
    cfg = load_config_dict(daemon_config_dict(port) | {"stereo": {"downsample": 2}, "queues": {"depth": 16}})
    pipe = PugsPipeline(core_of(cfg), seed=0)
    notifier = RecordingNotifier()
    dt = DaemonThread(Daemon(cfg, pipe, notifier=notifier)).start()
    try:
        wait_for(lambda: "READY=1" in notifier.sent, 10.0, "READY")
        cam = SyntheticCamera(client, cfg.topics)
        assert cam.wait_matching(10.0)
        for f in load_frames(str(sequence_npz)):
            cam.publish(f, time.time_ns())
            time.sleep(0.5)
        wait_for(lambda: dt.daemon.outputs.latest_grasps is not None, 180.0, "grasps", every_s=0.5)
        cam.close()
        # the daemon keeps training while idle (idle_train_s); compare after 150 streaming steps
        wait_for(
            lambda: pipe.svgp.total_steps >= 150,
            600.0,
            f"150 streaming steps (status: {dt.daemon.status()['counts']})",
            every_s=0.5,
        )
    finally:
        dt.stop()
    batch = PugsPipeline(core_of(cfg), seed=0)
    batch.store = copy.deepcopy(pipe.store)
    batch.fit_paper()
    q = pipe.query_cloud()
    _, s2_stream = pipe.sigma2_occ(q)
    _, s2_batch = batch.sigma2_occ(q)
    rho = float(spearmanr(s2_stream, s2_batch).statistic)
    msg = (
        f"daemon-trained streaming vs batch sigma2_occ on Q={len(q)} points of the daemon's "
        f"store ({len(pipe.store)} voxels, {pipe.svgp.total_steps} streaming steps): Spearman "
        f"{rho:.3f}"
    )
    print("\n" + msg)
    # a regression guard (a broken model gives about 0), not the target: the bench measures that.
    # Measured with M = 250: 0.674 and 0.697 alone, 0.591 once inside the slow suite (the daemon
    # trains between frames in real time, so the value moves between runs); 0.70 earlier at M = 500.
    assert rho > 0.5, msg
