"""The particle filter's shortcuts give the bits of the long way: the last step's batch reused (no stacking
of the tracks' samples), births matched on the free detections only (compacted per camera), the batch
computed in parts by threads."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from track_helpers import render_kp, ring_P, walkers

from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.split import Split, auto_threads, blas_single, blocked_matmul

CFG = ParticleConfig(motion="constant_velocity", n_samples=120, smooth_sigma_frames=0.0)


def _run(P, kp, sc, reuse: bool):
    tr = ParticleTracker(P, np.full(len(P), 1000.0), 25.0, CFG)
    out, reused = [], 0
    for t in range(len(kp)):
        if not reuse:
            tr._batch = None
        elif tr._batch is not None:
            reused += 1
        out.append(tr.step(kp[t], sc[t], t))
    return out, reused


def test_reused_batch_gives_the_same_bits():
    P = ring_P(4)
    X = walkers(3, 40, seed=5)
    kp, sc = render_kp(P, X, noise_px=1.5, seed=2, drop=0.05)
    a, reused = _run(P, kp, sc, reuse=True)
    b, _ = _run(P, kp, sc, reuse=False)
    assert reused > 20  # most frames had no birth or end: the batch was offered
    for ea, eb in zip(a, b, strict=True):
        assert np.array_equal(ea.track_id, eb.track_id)
        assert np.array_equal(ea.xyz_m, eb.xyz_m) and np.array_equal(ea.std_m, eb.std_m)


def test_births_on_compacted_free_detections_equal_the_full_frame():
    P = ring_P(4)
    X = walkers(3, 12, seed=7)
    kp, sc = render_kp(P, X, noise_px=1.5, seed=3, drop=0.05)
    # people enter one by one: births while other people are tracked (their detections not free)
    kp[:4, :, 1:], sc[:4, :, 1:] = np.nan, 0.0
    tr = ParticleTracker(P, np.full(len(P), 1000.0), 25.0, CFG)
    calls = []
    recon = tr.reconstructor

    def spy(kpf, scf):
        calls.append(kpf.shape[1])
        full = np.full((kpf.shape[0], kp.shape[2]) + kpf.shape[2:], np.nan)
        full_sc = np.zeros(full.shape[:3])
        full[:, : kpf.shape[1]], full_sc[:, : kpf.shape[1]] = kpf, scf
        a, b = recon(kpf, scf), recon(full, full_sc)  # compacted vs padded with empty slots
        assert np.array_equal(a.xyz_m, b.xyz_m, equal_nan=True) and np.array_equal(a.n_views, b.n_views)
        return a

    tr.reconstructor = type("R", (), {"__call__": staticmethod(spy), "flip": recon.flip})()
    ids = set()
    for t in range(len(kp)):
        ids |= set(tr.step(kp[t], sc[t], t).track_id.tolist())
    assert len(ids) == 3 and calls  # every person born
    assert min(calls) < kp.shape[2]  # with tracks alive, fewer slots than detections per camera


def _runs_by_threads(threads_list, frames: int = 30, block_rows: int = 50) -> dict:
    """The GRU prior's filter over ``frames`` frames of 4 walkers, for each number of threads; its products'
    fixed blocks of ``block_rows`` rows (480 rows: 9 blocks and a ragged 10th, so every count cuts)."""
    P = ring_P(4)
    X = walkers(4, frames, seed=11)
    kp, sc = render_kp(P, X, noise_px=1.5, seed=4, drop=0.05)
    runs = {}
    for threads in threads_list:
        cfg = ParticleConfig(n_samples=120, smooth_sigma_frames=0.0, threads=threads)  # the GRU prior
        tr = ParticleTracker(P, np.full(len(P), 1000.0), 25.0, cfg)
        tr.prior.block_rows = block_rows
        runs[threads] = [tr.step(kp[t], sc[t], t) for t in range(len(kp))]
    return runs


def _same_bits(a, b) -> bool:
    return all(
        np.array_equal(ea.track_id, eb.track_id)
        and len(ea.track_id) == 4
        and np.array_equal(ea.xyz_m, eb.xyz_m)
        and np.array_equal(ea.std_m, eb.std_m)
        and np.array_equal(ea.confidence, eb.confidence)
        for ea, eb in zip(a, b, strict=True)
    )


def test_batch_in_parts_by_threads_gives_the_same_bits(monkeypatch):
    cuts = []
    whole_map = Split.map

    def counted(self, fn, n, block=1):
        cuts.append(len(self.parts(n, block)))
        return whole_map(self, fn, n, block)

    monkeypatch.setattr(Split, "map", counted)
    runs = _runs_by_threads((1, 2, 3, 4))
    assert max(cuts) == 4  # the GRU's rows and the tracks were cut into parts
    for threads in (2, 3, 4):
        assert _same_bits(runs[1], runs[threads]), f"{threads} threads differ from 1"


def _has_avx2() -> bool:
    try:
        return "avx2" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


@pytest.mark.parametrize("coretype", ["Haswell", "Zen", "Sandybridge"])
def test_same_bits_by_threads_under_each_openblas_kernel(coretype):
    """OpenBLAS's Haswell and Zen kernels sum a row of a product in an order that depends on the product's
    shape: the filter's bits for 1-4 threads must not depend on it (a fixed partition of the products)."""
    if coretype != "Sandybridge" and not _has_avx2():
        pytest.skip(f"OpenBLAS's {coretype} kernels need AVX2, which this CPU lacks")
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); import test_track_particle_fastpaths as t; "
        "r = t._runs_by_threads((1, 2, 3, 4), frames=12); "
        "print([t._same_bits(r[1], r[k]) for k in (2, 3, 4)])"
    )
    env = {**os.environ, "OPENBLAS_CORETYPE": coretype}
    out = subprocess.run(
        [sys.executable, "-c", code, str(Path(__file__).parent)], capture_output=True, text=True, env=env
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[-2] == "[True, True, True]", out.stdout


def test_split_parts_cover_the_batch_in_order():
    for threads, n in [(2, 7), (3, 10), (4, 2), (2, 0), (8, 600)]:
        parts = Split(threads).parts(n)
        assert parts[0][0] == 0 and parts[-1][1] == n and len(parts) == max(1, min(threads, n))
        assert all(hi == lo2 for (_, hi), (lo2, _) in zip(parts, parts[1:], strict=False))
        assert max(hi - lo for lo, hi in parts) - min(hi - lo for lo, hi in parts) <= 1
    for threads, n, block in [(3, 10, 4), (2, 7, 3), (4, 1200, 256), (4, 0, 8), (2, 5, 8)]:
        parts = Split(threads).parts(n, block)  # whole blocks of a fixed partition, whatever the threads
        assert parts[0][0] == 0 and parts[-1][1] == n and len(parts) == max(1, min(threads, -(-n // block)))
        assert all(lo % block == 0 for lo, _ in parts)
    assert Split(0).threads >= 1


def test_blocked_products_give_the_bits_of_any_cut_at_a_block():
    a = np.random.default_rng(1).standard_normal((700, 114)).astype(np.float32)
    w = np.random.default_rng(2).standard_normal((114, 192)).astype(np.float32)
    with blas_single():
        whole = blocked_matmul(a, w, 256)
        for lo, hi in Split(3).parts(700, 256):
            assert np.array_equal(blocked_matmul(a[lo:hi], w, 256), whole[lo:hi])
        assert np.allclose(whole, a @ w, atol=1e-3)


def test_auto_threads_follow_the_cores_and_omp_num_threads(monkeypatch):
    monkeypatch.setattr("roomcap.track.split.available_cores", lambda: 16)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert auto_threads(0) == 4 and auto_threads(6) == 6  # auto up to 4; an explicit number as given
    monkeypatch.setenv("OMP_NUM_THREADS", "2")  # a worker's share when sessions run at once
    assert auto_threads(0) == 2 and auto_threads(3) == 3
    monkeypatch.setattr("roomcap.track.split.available_cores", lambda: 1)
    assert auto_threads(0) == 1


def test_threads_are_not_a_setting_the_outputs_depend_on():
    from roomcap.pipeline.config import PipelineConfig
    from roomcap.pipeline.stages import _result_settings

    def settings(options: dict) -> dict:
        config = PipelineConfig.from_dict({"track": {"tracker": "particle", "options": options}})
        return _result_settings(config.track)

    assert settings({"threads": 3}) == settings({}) != settings({"n_samples": 200})
