"""Place recognition for laser scans: which old scans may show the place a new one shows.

When the smoother's position is too uncertain for a loop-closure search around its
estimate (an outdoor loop of hundreds of metres drifts by tens), a revisit has to be
recognised from the scan alone. Each scan is summarised by a *polar key*, a coarse
picture of it from above (Kim & Kim's Scan Context, 2018, for a 2-D laser): its returns
within `range_m` binned into `rings` rings of equal width and `sectors` bearing sectors,
a cell 1 where a return fell; each sector's column is scaled to unit length. Two keys
are compared at every sector shift (the sensor may have turned): the mean over the
sectors either key saw of the columns' cosine, at the best shift (`similarities`,
all shifts at once by FFT). It uses the whole range of the laser (80 m where the
matcher uses 20), whose far structure is what tells places apart. Among the revisits of
a place (an old kept scan within 3 m and 1 rad, 20 m or more back along the path) the
three most similar keys held a true neighbour on freiburg-campus for 79 % (the ring key
it replaced, each ring's share of sectors with a return: 63 %) and on fhw for 74 %
(66 %) (BENCHMARKS.md). The candidates are then verified by matching
(slam.scan_graph).
"""

from __future__ import annotations

import math

import numpy as np

from hardware.messages import LaserScan


def polar_key(
    scan: LaserScan, rings: int = 20, sectors: int = 72, range_m: float = 80.0
) -> np.ndarray:
    """(rings, sectors) polar key of the scan (module docstring): a sector's column is
    unit length where the sector has a return within range_m, zero elsewhere."""
    r = np.asarray(scan.ranges, dtype=float)
    a = scan.angles
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r > 0) & (r < min(scan.range_max, range_m))
    ring = np.minimum((r[ok] / range_m * rings).astype(np.int64), rings - 1)
    sector = (np.mod(a[ok], 2 * math.pi) / (2 * math.pi) * sectors).astype(np.int64) % sectors
    key = np.zeros((rings, sectors), dtype=np.float32)
    key[ring, sector] = 1.0
    norms = np.sqrt(key.sum(axis=0))  # (a column of ones and zeros)
    return np.divide(key, norms, out=key, where=norms > 0)


def _spectra(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per key (N × rings × sectors): its columns' Fourier transform over the sectors,
    that of the sectors it saw, and how many it saw — all `similarities` needs of a key
    or a query, computed once per key in PlaceKeys."""
    seen = (keys > 0).any(axis=1).astype(np.float64)
    return np.fft.rfft(keys, axis=2), np.fft.rfft(seen, axis=1), seen.sum(axis=1)


def _similarities(keys: tuple, query: tuple, sectors: int) -> np.ndarray:
    """`similarities` from the keys' `_spectra` (N rows) and the query's (one row)."""
    keys_f, seen_f, seen_n = keys
    query_f, query_seen_f, query_n = query
    # circular cross-correlations over the sectors, every shift at once
    num = np.fft.irfft(np.einsum("nrk,rk->nk", keys_f, np.conj(query_f[0])), n=sectors, axis=1)
    both = np.fft.irfft(seen_f * np.conj(query_seen_f[0]), n=sectors, axis=1)
    either = seen_n[:, None] + query_n[0] - np.rint(both)
    return np.max(num / np.maximum(either, 1.0), axis=1)


def similarities(keys: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Per key (N × rings × sectors) its similarity to `query` at the best sector shift:
    max over shifts s of Σ_c cos(key[:, c], query[:, c − s]) / (sectors either saw),
    in [0, 1]; 0 where neither saw anything."""
    keys = np.asarray(keys, dtype=np.float32)
    if len(keys) == 0:
        return np.zeros(0)
    return _similarities(_spectra(keys), _spectra(np.asarray(query)[None]), keys.shape[2])


def _best(score: np.ndarray, count: int) -> np.ndarray:
    if len(score) == 0:
        return np.zeros(0, dtype=np.int64)
    count = min(count, len(score))
    part = np.argpartition(-score, count - 1)[:count]
    return part[np.argsort(-score[part], kind="stable")]


def nearest_places(keys: np.ndarray, query: np.ndarray, count: int) -> np.ndarray:
    """Row indices of the `count` keys most similar to `query` (`similarities`), most
    similar first."""
    return _best(similarities(keys, query), count)


class PlaceKeys:
    """The polar keys of a growing set of scans, kept as their spectra (`_spectra`),
    computed once when a key is added: a search over N old keys then costs one product
    per key instead of N transforms (`nearest`: the same answers as `nearest_places`)."""

    def __init__(self) -> None:
        self._arrays: tuple[np.ndarray, ...] = ()  # capacity doubles; rows ≥ size unused
        self._size = 0
        self._sectors = 0

    def __len__(self) -> int:
        return self._size

    def add(self, key: np.ndarray) -> int:
        """Store a key (rings × sectors); returns its row."""
        key = np.asarray(key, dtype=np.float32)
        spectra = _spectra(key[None])
        if not self._arrays:
            self._arrays = tuple(np.zeros((64, *a.shape[1:]), a.dtype) for a in spectra)
            self._sectors = key.shape[1]
        elif key.shape != (self._arrays[0].shape[1], self._sectors):
            raise ValueError(f"a polar key of shape {key.shape} does not match the stored keys")
        if self._size == len(self._arrays[0]):
            self._arrays = tuple(np.concatenate([a, np.zeros_like(a)]) for a in self._arrays)
        for stored, new in zip(self._arrays, spectra, strict=True):
            stored[self._size] = new[0]
        self._size += 1
        return self._size - 1

    def saw_anything(self, row: int) -> bool:
        """Whether the key at `row` has a return in any sector."""
        return bool(self._spectra([row])[2][0] > 0)

    def nearest(self, rows: np.ndarray, query: int, count: int) -> np.ndarray:
        """Of the stored keys at `rows`, the positions (into rows) of the `count` most
        similar to the stored key at row `query`, most similar first."""
        if len(rows) == 0:
            return np.zeros(0, dtype=np.int64)
        scores = _similarities(self._spectra(rows), self._spectra([query]), self._sectors)
        return _best(scores, count)

    def _spectra(self, rows) -> tuple[np.ndarray, ...]:
        rows = np.asarray(rows, dtype=np.int64)
        if rows.min() < 0 or rows.max() >= self._size:
            raise IndexError(f"rows must lie in [0, {self._size}), got {rows.min()}..{rows.max()}")
        return tuple(a[rows] for a in self._arrays)
