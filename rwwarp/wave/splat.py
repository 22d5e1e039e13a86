"""The splat stage of the ray-wave model (host side of :mod:`rwwarp.kernels.splat`): traced rays to the
complex field sampled on each source's wave-plane window.

:class:`Splatter` owns the launches of one tracer's device: ray-tube areas, the splat into per-sample
sums (float atomics; on CPU threads whole sources a thread, or private sums of ray ranges for fewer sources than
threads; the CPU's forward energy splat in separable form, :mod:`rwwarp.kernels.splat_forward`; or the deterministic
fixed-point passes), and
the finalize step (reference sphere and carrier). :meth:`rwwarp.wave.raywave.RayWave.field` calls it. Lengths
in mm.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels.splat import make_splat_kernels
from ..kernels.splat_forward import make_splat_forward_kernel
from .reduce import source_sums
from ..trace import run_chunks


class Splatter:
    """Splat launches on ``tracer``'s device, with gradients when the tracer records them.

    ``deterministic``: the same bits on every run on a GPU too: fixed-point sums (the rays' summed
    amplitudes as each source's bound, :data:`rwwarp.kernels.splat.FIXED_ONE`), the float splat recorded
    beside them for the adjoint, and tube areas from a stencil (:func:`~rwwarp.kernels.splat.stencil_kernel`)
    so their adjoint adds without contention."""

    def __init__(self, tracer, deterministic: bool = False):
        self.tracer = tracer
        self.K = make_splat_kernels(tracer.scalar)
        self.deterministic = bool(deterministic)
        self._ph = None

    def placeholders(self):
        """The kernels' deterministic-mode arguments when they are not used: (bound, int64 sums,
        amplitudes, tube-area stencil), made once."""
        if self._ph is None:
            dev, K = self.tracer.device, self.K
            self._ph = (wp.zeros((1, 1), dtype=K.vec4d, device=dev), wp.zeros(1, dtype=wp.int64, device=dev),
                        wp.zeros(1, dtype=K.vec4d, device=dev), wp.zeros((1, 5), dtype=self.tracer.K.vec3, device=dev))
        return self._ph

    def grid_placeholder(self):
        """The ``(1,)`` int32 per-source grid array of a launch that is not a packed batch."""
        a = self.__dict__.get("_ph_grid")
        if a is None:
            a = self._ph_grid = wp.zeros(1, dtype=wp.int32, device=self.tracer.device)
        return a

    def tube_areas(self, rays, n_side: int, rim_args, energy: bool, packed=None):
        """``(area, half)``: each ray's tube footprint on the plane (mm^2) and its box's half sizes (mm); in the
        paper convention (``energy`` False) placeholders the splat does not read. ``packed`` (a packed batch,
        ``n_side`` < 0): ``(sides, n_pupil, cell_stride)``, each source's pupil grid side (a Warp int32 array),
        its ray slots and the stride of its rim cells in ``rim_args``' table (0: one table)."""
        dev, K, g = self.tracer.device, self.K, self.tracer.requires_grad
        n = rays.pos.shape[0]
        if not energy and not g:
            return (wp.zeros(1, dtype=wp.float64, device=dev), wp.zeros(1, dtype=wp.vec2d, device=dev))
        if g:
            area = wp.zeros(n, dtype=wp.float64, device=dev, requires_grad=g)
            half = wp.zeros(n, dtype=wp.vec2d, device=dev, requires_grad=g)
        else:   # from the tracer's pool on a kept batch (Tracer.work_array); tube_area_kernel writes every ray's
            area = self.tracer.work_array("tube_area", n, wp.float64)
            half = self.tracer.work_array("tube_half", n, wp.vec2d)
        if packed is None:
            packed = (self.grid_placeholder(), 0, 0)
        if energy:
            if self.deterministic:   # neighbours' positions handed over by each ray (an adjoint without contention)
                nbr = wp.zeros((n, 5), dtype=rays.pos.dtype, device=dev, requires_grad=g)
                wp.launch(K.stencil_kernel, dim=n, inputs=[rays.pos, n_side, packed[0], packed[1]], outputs=[nbr],
                          device=dev)
            else:
                nbr = self.placeholders()[3]
            wp.launch(K.tube_area_kernel, dim=n,
                      inputs=[rays.pos, rays.valid, n_side, *rim_args, int(self.deterministic), nbr, *packed],
                      outputs=[area, half], device=dev)
        return area, half

    def sums(self, splat_in, n_src: int, n_grid: int, source_work=None):
        """``(s_re, s_im, dropped)``: the splat's per-sample sums (n_src * n_grid^2 float64 each) and the rays
        per source that fell outside the window. ``splat_in``: the splat kernel's inputs up to its
        ``frac_stride`` argument (:meth:`rwwarp.wave.raywave.RayWave.field` forms them). ``n_grid``: the windows'
        side (a packed batch: the slots' side; its own sides are in ``splat_in``). ``source_work`` (CPU threads;
        None: ray ranges): each source's relative cost, (n_src,); with at least as many sources as threads the
        threads take whole sources (:func:`source_groups`) and add into the one set of sums."""
        tr, K = self.tracer, self.K
        dev, g = tr.device, tr.requires_grad
        n_rays = splat_in[0].shape[0]
        total = n_src * n_grid * n_grid
        if g:
            s_re = wp.zeros(total, dtype=wp.float64, device=dev, requires_grad=g)
            s_im = wp.zeros(total, dtype=wp.float64, device=dev, requires_grad=g)
        else:   # from the tracer's pool on a kept batch (Tracer.work_array)
            s_re = tr.work_array("splat_re", total, wp.float64, zero=True)
            s_im = tr.work_array("splat_im", total, wp.float64, zero=True)
        dropped = wp.zeros(n_src, dtype=wp.int32, device=dev)   # new each run: RayWave.dropped outlives the run
        nb, na, nv, _ = self.placeholders()
        if self.deterministic:
            self._fixed(splat_in, s_re, s_im, dropped, n_src, n_grid)
            return s_re, s_im, dropped
        chunks = tr._chunks(n_rays)
        # the CPU's forward energy splat: the separable form (rwwarp.kernels.splat_forward, the same sums to a few
        # units of the last place; no adjoint, none is recorded here). Not in the forward-only pass of a tracer built
        # for gradients (Tracer.recordable_pass): a checkpointed tile recomputes it under a tape with splat_kernel,
        # and its two passes give the same bits
        forward = dev == "cpu" and not g and not tr.recordable_pass and splat_in[15] >= 1

        def launch(first: int, count: int, out):
            if forward:
                wp.launch(make_splat_forward_kernel(tr.scalar), dim=count, inputs=splat_in + [first],
                          outputs=list(out[:3]), device=dev)
            else:
                wp.launch(K.splat_kernel, dim=count, inputs=splat_in + [first, 0, nb],
                          outputs=list(out[:3]) + [na, na, nv], device=dev)
        if len(chunks) == 1:
            launch(0, n_rays, (s_re, s_im, dropped))
            return s_re, s_im, dropped
        kern = (make_splat_forward_kernel(tr.scalar) if forward else K.splat_kernel,)
        groups = source_groups(source_work, n_src, len(chunks)) if source_work is not None else None
        if groups is not None:
            # CPU threads take whole sources: a source's rays add only into its own window and counter, so the
            # threads share the sums with no race, and each sample adds its rays in the order one launch does
            npup = n_rays // n_src
            run_chunks(lambda c, _: launch(c[0] * npup, (c[1] - c[0]) * npup, (s_re, s_im, dropped)),
                       groups, [None] * len(groups), kernels=kern, device=dev)
            return s_re, s_im, dropped
        # CPU threads splat ray ranges into private sums (Warp's CPU atomics are plain adds), then add
        parts = [(s_re, s_im, dropped)] + [
            (wp.zeros(total, dtype=wp.float64, device=dev), wp.zeros(total, dtype=wp.float64, device=dev),
             wp.zeros(n_src, dtype=wp.int32, device=dev)) for _ in chunks[1:]]
        run_chunks(lambda c, out: launch(c[0], c[1] - c[0], out), chunks, parts, kernels=kern, device=dev)
        for a, b, d in parts[1:]:
            s_re.numpy()[:] += a.numpy()
            s_im.numpy()[:] += b.numpy()
            dropped.numpy()[:] += d.numpy()
        return s_re, s_im, dropped

    def _fixed(self, splat_in, s_re, s_im, dropped, n_src: int, n_grid: int):
        """The deterministic passes (see :mod:`rwwarp.kernels.splat`): the rays' amplitudes summed per source by
        the fixed tree give each source's bound; the contributions are added as int64 in units of
        ``bound / FIXED_ONE`` and converted back into ``s_re``, ``s_im``. Under a tape the float splat is
        recorded first (its adjoint only reads the samples' gradients); its sums are overwritten."""
        K, dev = self.K, self.tracer.device
        n_rays = splat_in[0].shape[0]
        total = n_src * n_grid * n_grid
        nb, na, nv, _ = self.placeholders()
        scratch = wp.zeros(n_src, dtype=wp.int32, device=dev)   # the passes other than the counted one
        if self.tracer.requires_grad:
            wp.launch(K.splat_kernel, dim=n_rays, inputs=splat_in + [0, 0, nb],
                      outputs=[s_re, s_im, scratch, na, na, nv], device=dev)
        amps = wp.zeros(n_rays, dtype=K.vec4d, device=dev)
        wp.launch(K.splat_kernel, dim=n_rays, inputs=splat_in + [0, 2, nb],
                  outputs=[s_re, s_im, scratch, na, na, amps], device=dev, record_tape=False)
        bound = source_sums(amps, n_src, wp.float64, dev)
        acc_re = wp.zeros(total, dtype=wp.int64, device=dev)
        acc_im = wp.zeros(total, dtype=wp.int64, device=dev)
        wp.launch(K.splat_kernel, dim=n_rays, inputs=splat_in + [0, 1, bound],
                  outputs=[s_re, s_im, dropped, acc_re, acc_im, nv], device=dev, record_tape=False)
        wp.launch(K.fixed_to_float_kernel, dim=total, inputs=[acc_re, acc_im, bound, n_grid * n_grid],
                  outputs=[s_re, s_im], device=dev, record_tape=False)

    def finalize(self, fin_in, total: int):
        """The field (``total`` vec2d samples) from the sums: ``fin_in`` the finalize kernel's inputs up to its
        ``offset`` argument (reference sphere and carrier applied; CPU threads take sample ranges)."""
        tr, K = self.tracer, self.K
        dev, g = tr.device, tr.requires_grad
        # the finalize kernel writes every sample
        field = wp.zeros(total, dtype=wp.vec2d, device=dev, requires_grad=True) if g else \
            tr.work_array("field", total, wp.vec2d)
        chunks = tr._chunks(total)
        # forward only: a sample no ray reached is written 0 without forming its phase (the same value)
        skip = 0 if g else 1
        run_chunks(lambda c, _: wp.launch(K.finalize_kernel, dim=total if c is None else c[1] - c[0],
                                          inputs=fin_in + [skip, 0 if c is None else c[0]], outputs=[field],
                                          device=dev),
                   chunks, [None] * len(chunks), kernels=(K.finalize_kernel,), device=dev)
        return field


def source_groups(work, n_src: int, n_threads: int):
    """Contiguous source ranges ``[(lo, hi), ...]``, one per CPU thread, of about equal summed ``work``
    ((n_src,) relative cost of each source, e.g. its window's samples); None when there are fewer sources than
    threads (the caller splits rays instead)."""
    if n_threads <= 1 or n_src < n_threads:
        return None
    w = np.maximum(np.asarray(work, dtype=np.float64).reshape(n_src), 0.0)
    c = np.concatenate([[0.0], np.cumsum(w)])
    if not c[-1] > 0:
        c = np.arange(n_src + 1, dtype=np.float64)
    cuts = [0]
    for t in range(1, n_threads):
        k = int(np.searchsorted(c, c[-1] * t / n_threads))
        cuts.append(min(max(k, cuts[-1] + 1), n_src - (n_threads - t)))
    cuts.append(n_src)
    return [(cuts[t], cuts[t + 1]) for t in range(n_threads)]


def paper_rescale(u, traced_power, pitch_mm: float, xp, cosines=None):
    """The paper's amplitude convention: rays of unit amplitude, then one scale per source so that the
    field's power ``sum |u|^2 pitch^2`` (pitch in mm) equals the traced power (the power of the valid
    rays). ``u`` (S, n, n) complex and ``traced_power`` (S,) in one array namespace ``xp`` (numpy,
    CuPy or torch: the same formula differentiates in torch); a source with no field power stays zero.
    ``cosines`` (pixel_values "flux"): the direction cosines ``k_z / k`` on an (S, N, N) FFT grid of the windows
    (:func:`rwwarp.wave.focal.plane_direction_cosines`, in ``xp``): the field's z-flux through the plane,
    ``sum c |F u|^2 pitch^2 / N^2``, is made the traced power instead."""
    if cosines is not None:
        N = cosines.shape[-1]
        s = xp.fft.fft2(u, s=(N, N))
        pw = (cosines * (s.real ** 2 + s.imag ** 2)).sum((1, 2)) * pitch_mm ** 2 / (N * N)
    else:
        pw = (u.real ** 2 + u.imag ** 2).sum((1, 2)) * pitch_mm ** 2   # pitch_mm: a number or one per source
    ok = pw > 0
    return u * xp.where(ok, xp.sqrt(traced_power / xp.where(ok, pw, 1.0)), 0.0)[:, None, None]


def plane_cosines(rw, xp=np, like=None):
    """pixel_values "flux": the direction cosines ``k_z / k`` (S, 2n, 2n) on the FFT grid of a RayWave's windows
    (``n`` the window slot), in ``xp`` (numpy, CuPy or torch), for the paper convention's flux normalisation
    (:func:`paper_rescale`); None with "intensity"."""
    if rw.pixel_values != "flux":
        return None
    from .focal import plane_direction_cosines
    lay = rw._layout()
    return _in(xp, plane_direction_cosines(2 * lay["n_stride"], lay["pitches"], rw.carrier, rw.lam_mm / rw.n_after), like)


def _in(xp, a, like=None):
    """Host array ``a`` in namespace ``xp`` (numpy, CuPy, or torch on the device of the tensor ``like``)."""
    if getattr(xp, "__name__", "") == "torch":
        return xp.as_tensor(a, device=None if like is None else like.device)
    return xp.asarray(a)


def paper_rescale_layout(rw, u, traced_power, xp):
    """:func:`paper_rescale` for the sources of RayWave ``rw`` (a batch on one plan, or a packed batch of members on
    their own plans): one scale per source at its own pitch; with pixel_values "flux" each source's z-flux on the
    FFT grid of its own window (``2 n_k``), as the source alone has it (the cosine-weighted sum over a larger
    slot's grid is another quadrature of the same spectrum: ~1e-6 apart). ``u`` (S, n, n) and ``traced_power``
    (S,) in ``xp`` (numpy, CuPy or torch)."""
    lay = rw._layout()
    if lay["ray_grids"] is None:
        return paper_rescale(u, traced_power, rw.plan.pitch_mm, xp, plane_cosines(rw, xp, u))
    pitches = np.asarray(lay["pitches"], dtype=np.float64)
    if rw.pixel_values != "flux":
        return paper_rescale(u, traced_power, _in(xp, pitches, u), xp)
    from .focal import plane_direction_cosines
    lam = np.asarray(rw.lam_mm, dtype=np.float64) / np.asarray(rw.n_after, dtype=np.float64)
    carrier = np.asarray(rw.carrier, dtype=np.float64)
    out = xp.zeros_like(u)
    for k in range(u.shape[0]):
        n = int(lay["grids"][k])
        c = _in(xp, plane_direction_cosines(2 * n, pitches[k:k + 1], carrier[k:k + 1], lam[k:k + 1]), u)
        out[k:k + 1, :n, :n] = paper_rescale(u[k:k + 1, :n, :n], traced_power[k:k + 1], float(pitches[k]), xp, c)
    return out
