"""The save path's shortcuts give numpy's own figures bit for bit (issue 23, stop 44)."""

import numpy as np
import pytest

from nplps.reconstruction import _median_p90


def _samples(rng: np.random.Generator, n: int, kind: int, dtype: type) -> np.ndarray:
    if kind == 0:
        return (rng.random(n) * rng.uniform(0.1, 100.0)).astype(dtype)
    if kind == 1:  # many ties: the ranks land inside runs of equal values
        return (rng.integers(0, 5, n) * 0.3).astype(dtype)
    return (rng.standard_exponential(n) ** 3).astype(dtype)  # heavy tail, as the held-out errors


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_median_p90_is_numpys_bit_for_bit(seed: int, dtype: type) -> None:
    rng = np.random.default_rng(seed)
    sizes = [*range(1, 130), 1000, 4097, 65_537, int(rng.integers(100_000, 300_000))]
    for n in sizes:
        for kind in range(3):
            values = _samples(rng, n, kind, dtype)
            wide = values.astype(np.float64)
            expected = (float(np.median(wide)), float(np.percentile(wide, 90)))
            got = _median_p90(values.copy())
            assert got == expected, (n, kind, got, expected)


def _old_trust_figures(sigma_map: np.ndarray, held_map: np.ndarray, mask: np.ndarray) -> dict:
    """summary.json's trust figures as main computed them (float64 copies, numpy's median/percentile)."""
    inside = mask & np.isfinite(sigma_map) & np.isfinite(held_map)
    sigma = sigma_map[inside].astype(np.float64)
    held = held_map[inside].astype(np.float64)
    return {
        "pixels": int(sigma.size),
        "normal_sigma_deg": {
            "median": float(np.median(sigma)),
            "p90": float(np.percentile(sigma, 90)),
            "rms": float(np.sqrt(np.mean(sigma**2))),
        },
        "held_out_error": {
            "mean": float(np.mean(held)),
            "median": float(np.median(held)),
            "p90": float(np.percentile(held, 90)),
        },
    }


@pytest.mark.parametrize("seed", range(4))
def test_trust_summary_is_mains_bit_for_bit(seed: int) -> None:
    from types import SimpleNamespace

    from nplps.reconstruction import Reconstruction

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(50, 400)), int(rng.integers(50, 400))
    sigma = (rng.standard_exponential((h, w)) * rng.uniform(0.01, 5)).astype(np.float32)
    held = (rng.standard_exponential((h, w)) ** 2 * 1e-3).astype(np.float32)
    sigma[rng.random((h, w)) < 0.05] = np.nan  # left out, as the maps' unknown pixels
    held[rng.random((h, w)) < 0.05] = np.inf
    mask = rng.random((h, w)) < 0.8
    fake = SimpleNamespace(normal_sigma=sigma, held_out_error=held, mask=mask, light_trust=None)
    got = Reconstruction._trust_summary(fake)  # type: ignore[arg-type]
    assert got is not None
    assert got.pop("lights") == []
    assert got == _old_trust_figures(sigma, held, mask)
