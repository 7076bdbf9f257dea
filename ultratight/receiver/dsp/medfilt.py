"""A running median over a periodic sequence (the CW excision's local spectrum level, acquisition).

Each output is the median of the ``win`` (odd) entries centred on it, the sequence taken as periodic
(``scipy.ndimage.median_filter(v, size=win, mode="wrap")`` computes the same; scipy.ndimage is not
imported for it). The entries are ranked once (one sort); a Fenwick tree (binary indexed tree) over
the ranks counts the entries inside the window as it slides, and the median is the window's
``win // 2``-th rank, found by one descent of the tree: O(n log n) in all, about a millisecond for a
spectrum of 40 000 bins whatever the window.
"""

import numba
import numpy as np


@numba.njit(cache=True)
def _slide(ext, order, win, out):
    m = ext.size
    rank = np.empty(m, np.int64)
    for r in range(m):
        rank[order[r]] = r
    tree = np.zeros(m + 1, np.int64)             # Fenwick tree over ranks 1..m
    top = 1
    while top * 2 <= m:
        top *= 2
    for i in range(win):
        r = rank[i] + 1
        while r <= m:
            tree[r] += 1
            r += r & -r
    want = win // 2 + 1                          # the median's place in the window, from 1
    for i in range(out.size):
        pos, left, step = 0, want, top           # descend: the smallest rank with `want` entries up to it
        while step:
            nxt = pos + step
            if nxt <= m and tree[nxt] < left:
                pos = nxt
                left -= tree[nxt]
            step //= 2
        out[i] = ext[order[pos]]
        if i + 1 == out.size:
            break
        r = rank[i] + 1                          # the entry leaving the window
        while r <= m:
            tree[r] -= 1
            r += r & -r
        r = rank[i + win] + 1                    # the entry entering it
        while r <= m:
            tree[r] += 1
            r += r & -r


def running_median_wrap(v, win):
    """Median of each ``win`` (odd, ≥ 1) consecutive entries of the 1-D ``v`` centred on it, ``v``
    periodic; same dtype as ``v``."""
    v = np.asarray(v)
    win = int(win)
    if win < 1 or win % 2 == 0:
        raise ValueError(f"running median: the window must be odd and >= 1, got {win}")
    h = win // 2
    ext = np.concatenate([v[np.arange(-h, 0) % v.size], v, v[np.arange(h) % v.size]])
    out = np.empty(v.size, dtype=v.dtype)
    _slide(ext, np.argsort(ext), win, out)
    return out
