"""The progressive rounds of splatting: doubling schedules and the pixel-rank pseudo-rounds.
"""

from __future__ import annotations


import numba


__all__ = ['doubling_schedule']

# ----------------------------------------------------------------------------
# Round schedules
# ----------------------------------------------------------------------------

def doubling_schedule(total_spp: int, initial_spp: int = 1) -> list[int]:
    """Round sizes N_0 = initial_spp, N_j = 2 N_{j-1} (Fig. 3) summing to ``total_spp``.

    The last round absorbs the remainder when it is smaller than the next
    doubling (no round is smaller than its predecessor): 4 spp -> [1, 3],
    64 spp -> [1, 2, 4, 8, 16, 33].
    """
    total_spp = int(total_spp)
    out = []
    done = 0
    while done < total_spp:
        out.append(_next_round(total_spp - done, out[-1] if out else None, initial_spp))
        done += out[-1]
    return out


def _next_round(rem: int, prev, initial_spp: int) -> int:
    if prev is None:
        return min(int(initial_spp), rem)
    n = max(1, int(round(2 * prev)))
    if n >= rem or rem - n < 2 * n:
        return rem
    return n


@numba.njit(cache=True, nogil=True)
def _select_by_rank(pix, rank, lo, hi, mask):
    """Mark samples whose running per-pixel rank lies in [lo[p], hi[p]); advances rank."""
    for k in range(pix.shape[0]):
        p = pix[k]
        r = rank[p]
        mask[k] = r >= lo[p] and r < hi[p]
        rank[p] = r + 1
