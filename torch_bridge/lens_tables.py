"""The lens's parameter table and DOE phase, built in torch from :class:`torch_bridge.modules.HybridLens`'s values.

:class:`LensTables` is a mixin of :class:`~torch_bridge.modules.HybridLens` (split out of ``modules.py`` to keep
files short): the differentiable pieces that turn the module's quantities (``values()``) into what the trace
and the propagation take -- the tracer's parameter table with the thin lenses' conjugates
(:meth:`LensTables.param_table`), its host copy (:meth:`LensTables.host_table`) and the DOE's relief phase on
each window (:meth:`LensTables.doe_phase`). It reads the HybridLens attributes ``values()``,
``standard_mask``, ``thin_mask``, ``phase_mask``, ``_thin_surfaces``, ``_phase_surfaces``, ``doe_kind``,
``doe_base`` and ``_pixel_pitch``. Units: mm, rad, 1/mm.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from rwwarp.trace import COLUMNS as COL

from rwwarp import doe
from rwwarp.lens import MAX_ASPHERIC

from . import phase_params as _ph
from .functions import bridge_state, quantize_ste, upload

__all__ = ["LensTables"]

# the table's first columns are z, curvature, conic and the aspheric terms, in that order (rwwarp.kernels.trace's
# layout): param_table writes them as one block, [0, _HEAD)
_HEAD = COL.asph0 + COL.n_asph
_CONTIGUOUS = (COL.z == 0 and COL.curvature == 1 and COL.conic == 2 and COL.asph0 == 3 and COL.n_asph <= MAX_ASPHERIC)


class LensTables:
    """Mixin of :class:`~torch_bridge.modules.HybridLens`: parameter table, host table and DOE phase in torch
    (see the module docstring)."""

    def param_table(self, rw, values=None) -> torch.Tensor:
        """The tracer's parameter table (n_surfaces + 1, N_PARAMS) as a float64 tensor built from
        the current values (vertex z = cumulative thickness, curvature, conic, aspheric; thin lens
        power and conjugates, see the module docstring). ``rw``: a RayWave made by :meth:`raywave`, or a
        Tracer whose ``bridge_state`` holds a ``base_table`` (no ``tracer``: thin-lens conjugates stay at the
        table's)."""
        v = values or self.values()
        dev = v["thickness"].device
        st = bridge_state(rw)
        on_dev = st.setdefault("base_table_on", {})   # one upload per device, not one per call
        base = on_dev.get(dev)
        if base is None:
            base = on_dev[dev] = upload(st["base_table"], torch.float64, dev)
        t = v["thickness"]
        zero = torch.zeros(1, dtype=t.dtype, device=dev)
        std = self._std_rows(dev)
        if _CONTIGUOUS:
            # z, curvature, conic and the aspheric terms are the table's first columns: the standard surfaces'
            # values put in by one selection over that block and the table joined in one concatenation (6
            # operations, each a GPU launch, instead of ~22: issue 25); the same values as column by column
            learned = F.pad(torch.cat([v["curvature"][:, None], v["conic"][:, None],
                                       v["aspheric"][:, :COL.n_asph]], 1), (0, 0, 0, 1))
            z = F.pad(torch.cumsum(t, 0), (1, 0))          # surfaces 0..n-1, then the sensor (at the sum)
            mid = torch.where(std[:, None], learned, base[:, COL.curvature:_HEAD])
            table = torch.cat([z[:, None], mid, base[:, _HEAD:]], 1)
            if not (any(self._phase_surfaces) or any(self._thin_surfaces)):
                return table
            cols = list(table.unbind(1))
        else:
            z = torch.cat([zero, torch.cumsum(t, 0)])  # surfaces 0..n-1, then the sensor
            cols = [base[:, j] for j in range(COL.n_params)]
            cols[COL.z] = z
            cols[COL.curvature] = torch.where(std, torch.cat([v["curvature"], zero]), cols[COL.curvature])
            cols[COL.conic] = torch.where(std, torch.cat([v["conic"], zero]), cols[COL.conic])
            asph = torch.cat([v["aspheric"], torch.zeros(1, MAX_ASPHERIC, dtype=t.dtype, device=dev)])
            for k in range(COL.n_asph):
                cols[COL.asph0 + k] = torch.where(std, asph[:, k], cols[COL.asph0 + k])
        if any(self._phase_surfaces):
            _ph.write_phase_columns(cols, v["phase"], self.phase_mask)
        if any(self._thin_surfaces):
            thin = torch.cat([self.thin_mask.to(dev), torch.zeros(1, dtype=torch.bool, device=dev)])
            if hasattr(rw, "tracer"):
                power, uinv, vdist = self._thin_lens_columns(rw, v)
                cols[COL.uinv] = torch.where(thin, torch.cat([uinv, zero]), cols[COL.uinv])
                cols[COL.v] = torch.where(thin, torch.cat([vdist, zero]), cols[COL.v])
            else:
                # no tracer to take indices from (a Tracer with only a base table): the power
                # follows the focal length, the conjugates (path length only, not ray geometry) stay
                f = torch.where(self.thin_mask.to(dev), v["focal_length"], torch.ones_like(v["focal_length"]))
                power = 1.0 / f
            cols[COL.power] = torch.where(thin, torch.cat([power, zero]), cols[COL.power])
        return torch.stack(cols, dim=1)

    def _std_rows(self, dev) -> torch.Tensor:
        """The standard surfaces' rows of the table (bool (n_surfaces + 1,), the sensor row False) on ``dev``, made
        once per device."""
        memo = self.__dict__.setdefault("_std_rows_on", {})
        got = memo.get(dev)
        if got is None or got.shape[0] != self.standard_mask.shape[0] + 1:
            got = memo[dev] = torch.cat([self.standard_mask.to(dev), torch.zeros(1, dtype=torch.bool, device=dev)])
        return got

    def _thin_lens_columns(self, rw, v):
        """Power 1/f (1/mm), object-side 1/u (1/mm, 0 = infinity) and image distance v (mm) of every
        surface (meaningful on thin lenses; (n_surfaces,) each), differentiable: the paraxial y-nu
        trace of :func:`rwwarp.paraxial.thin_lens_conjugates` in torch (indices at the tracer's first
        wavelength; DOE powers taken from the lens as fixed numbers)."""
        from rwwarp import paraxial
        lens = rw.tracer.lens
        wl0 = rw.tracer.wavelengths_um[0]
        st = bridge_state(rw)
        const = st.get("paraxial")
        if const is None:
            n = lens.indices(wl0)
            n_before = np.concatenate([[paraxial.object_index(lens, wl0)], n[:-1]])
            doe_p = np.array([paraxial.doe_power(s, wl0) if s.type == "doe" else 0.0 for s in lens.surfaces])
            const = {"n": n, "n_before": n_before, "doe_power": doe_p, "object_distance": lens.object_distance}
            st["paraxial"] = const
        dev, dt = v["thickness"].device, torch.float64
        n = upload(const["n"], dt, dev)
        n_before = upload(const["n_before"], dt, dev)
        std = self.standard_mask.to(dev)
        thin = self.thin_mask.to(dev)
        f = torch.where(thin, v["focal_length"], torch.ones_like(v["focal_length"]))
        power = torch.where(std, (n - n_before) * v["curvature"],
                            torch.where(thin, 1.0 / f, upload(const["doe_power"], dt, dev)))
        if any(self._phase_surfaces):   # rwwarp.paraxial.surface_powers: a standard surface's phase adds its power
            power = power + _ph.phase_powers(lens, v["phase"], wl0)
        od = const["object_distance"]
        one = torch.ones((), dtype=dt, device=dev)
        y0, nu0 = (one, 0.0 * one) if math.isinf(od) else (od * one, one)
        ys, nus_in, _ = paraxial.ynu_steps(power, v["thickness"], n, y0, nu0)   # rwwarp's trace, in torch
        uinv, vdist = [], []
        for i in range(len(lens.surfaces)):
            if self._thin_surfaces[i]:
                ui = torch.where(nus_in[i].abs() < 1e-300, 0.0 * one, nus_in[i] / (n_before[i] * ys[i]))
                uinv.append(ui)
                vdist.append(n[i] / (power[i] - n_before[i] * ui))
            else:
                uinv.append(0.0 * one)
                vdist.append(0.0 * one)
        return torch.where(thin, power, torch.zeros_like(power)), torch.stack(uinv), torch.stack(vdist)

    def doe_phase(self, rw, values=None, wrap: bool = True):
        """DOE relief phase phi0 (rad) on each window of ``rw``, (S, n, n) float64, built in torch from
        the DOE values (wrapped to [0, 2 pi), quantised with a straight-through gradient when the
        surface has ``levels``; not masked at the DOE's edge): the same samples as
        :meth:`rwwarp.psf.RayWave.doe_phase`. None without a DOE. ``wrap=False``: the smooth unwrapped
        phase (the focal path's diffraction orders, :func:`~torch_bridge.functions.doe_orders_factor`)."""
        s = rw.lens.surfaces[rw.plane]
        if s.type != "doe":
            return None
        v = (values or self.values())["doe"]
        dev = v.device
        st = bridge_state(rw)
        geo = st.get("doe_geometry")
        if geo is None or geo["device"] != dev:
            geo = self._doe_geometry(rw, s, dev)
            st["doe_geometry"] = geo
        kind = self.doe_kind
        # the forward is rwwarp.doe's (the numpy profiles evaluate the same functions), in torch
        if kind == "zernike":
            basis = geo["basis"]
            phi = torch.tensordot(v, basis, dims=1) if v.numel() else torch.zeros(basis.shape[1:], dtype=v.dtype,
                                                                                   device=dev)
        elif kind == "pixel_map":
            phi = doe.pixel_map_phase(v, geo["row"], geo["col"], geo["in_map"], torch)
        else:
            # from the separable x (S, 1, n), y (S, n, 1): a cached (S, n, n) radius per plan would cost more
            # memory than the whole training step
            phi = doe.profile_phase(kind, v, geo["x"], geo["y"], norm_radius=s.profile.get("norm_radius"),
                                    design_wavelength_um=s.design_wavelength_um, xp=torch)
        # no mask at the DOE's edge (as rwwarp.psf): rays are clipped there by the tracer
        return quantize_ste(phi, s.levels) if wrap else phi

    def _doe_geometry(self, rw, s, dev):
        """Per-plan DOE sampling helpers, built on ``dev`` by rwwarp.doe's functions in torch (no
        window-sized host-to-device copies): the separable coordinates, the Zernike
        basis ``Z_j`` (one (S, n, n) map per coefficient: the phase is linear in them), a pixel map's
        nearest-pixel indices."""
        from .functions import _grid_points
        x, y = _grid_points(rw, dev)
        geo = {"device": dev}
        kind = self.doe_kind
        if kind == "zernike":
            m = self.doe_base.numel()
            basis = x.new_empty((m,) + torch.broadcast_shapes(x.shape, y.shape))
            for j in range(m):
                e = [0.0] * m
                e[j] = 1.0
                basis[j] = doe.zernike_phase(e, float(s.profile["norm_radius"]), x, y, torch)
            geo["basis"] = basis
        elif kind == "pixel_map":
            ind = doe.pixel_map_indices(self._pixel_pitch, self.doe_base.shape, x, y, torch)
            geo["row"], geo["col"], geo["in_map"] = ind
        else:
            geo["x"], geo["y"] = x, y                    # (S, 1, n), (S, n, 1)
        return geo

    def host_table(self, rw, table, tables: dict | None = None) -> np.ndarray:
        """``table`` (:meth:`param_table` of ``rw``) as a float64 numpy array. ``tables``: a dict the caller
        keeps for one set of values (one :meth:`psf_map` or provider call, its recomputation included):
        sources with the same base table share one device-to-host copy (each copy waits for the device
        to finish its queue, so one per source would serialise host and device)."""
        if tables is None:
            return table.detach().to("cpu", torch.float64).numpy()
        # without thin lenses the table is the base table with the values written in; with them its thin-lens
        # columns also depend on the RayWave (wavelength, conjugates)
        key = id(rw) if any(self._thin_surfaces) else bridge_state(rw)["base_table"].tobytes()
        out = tables.get(key)
        if out is None:
            out = tables[key] = table.detach().to("cpu", torch.float64).numpy()
        return out
