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
