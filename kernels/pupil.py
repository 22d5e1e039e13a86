"""Pupil-cell geometry shared by ray generation and splatting (Warp functions, float64).

A full ``n x n`` cell-centre pupil grid over [-1, 1]^2 covers the unit-disc pupil with square cells of
side ``2 / n``. A cell cut by the rim is only partly inside: :func:`disc_cell_coverage` gives the
covered fraction of the cell and the centroid of the covered part, so the ray that represents the
cell starts at that centroid and carries the covered fraction of the cell's power, and its ray tube
on the wave plane is shrunk by the same fraction. The circular edge is then integrated to
second order in the cell size instead of as a staircase of whole cells.

The fraction is integrated over ``COVERAGE_COLUMNS`` columns (midpoint rule in x), each with its
exact covered y-interval, so the error in a cut cell's fraction is ~1e-3 of the cell.
"""
import warp as wp

COVERAGE_COLUMNS = 32  # the literal in the loop below


@wp.func
def disc_cell_coverage(pu: wp.float64, pv: wp.float64, side: wp.float64):
    """(fraction, centroid u, centroid v) of the cell [pu +- side/2] x [pv +- side/2] inside the unit disc."""
    h = wp.float64(0.5) * side
    ru = wp.abs(pu) + h
    rv = wp.abs(pv) + h
    if ru * ru + rv * rv <= wp.float64(1.0):
        return wp.vec3d(wp.float64(1.0), pu, pv)          # wholly inside
    lu = wp.max(wp.abs(pu) - h, wp.float64(0.0))
    lv = wp.max(wp.abs(pv) - h, wp.float64(0.0))
    if lu * lu + lv * lv >= wp.float64(1.0):
        return wp.vec3d(wp.float64(0.0), pu, pv)          # wholly outside
    total = wp.float64(0.0)
    mu = wp.float64(0.0)
    mv = wp.float64(0.0)
    dx = side / wp.float64(32.0)
    for col in range(32):
        x = pu - h + (wp.float64(col) + wp.float64(0.5)) * dx
        if x * x < wp.float64(1.0):
            s = wp.sqrt(wp.float64(1.0) - x * x)
            lo = wp.max(pv - h, -s)
            hi = wp.min(pv + h, s)
            if hi > lo:
                ln = hi - lo
                total = total + ln
                mu = mu + x * ln
                mv = mv + wp.float64(0.5) * (lo + hi) * ln
    if total <= wp.float64(0.0):
        return wp.vec3d(wp.float64(0.0), pu, pv)
    return wp.vec3d(total * dx / (side * side), mu / total, mv / total)
