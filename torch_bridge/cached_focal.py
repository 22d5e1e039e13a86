"""The focal-method entries of :class:`torch_bridge.design.CachedProvider` (split out of ``design.py``, which it
completes; nothing here is used alone): the choice of the focal method for an entry, the entry's pilot trace, its
build (one RayWave and cached wave-plane field a node), its PSFs from the current DOE and its sampling check.

Units: mm, um for wavelengths, degrees for fields, radians for DOE coefficients.
"""
from __future__ import annotations

import numpy as np
import torch

from rwwarp.wave.methods import PLANNER_CHOICES, get as get_method, names
from torch_bridge.budget import focal_graph_bytes

from .wave_step import add_wave_step

__all__ = ["FocalEntries"]


class FocalEntries:
    """Methods of :class:`~torch_bridge.design.CachedProvider` for its focal entries (``self._focal``: key ->
    ``(nodes, distance_mm, geometry)``); a mixin, it uses the provider's attributes (``module``, ``plans``,
    ``size``, ``pixel_mm``, ``build_log``, ``step_log``, ``replan_log``, ``_geometry``, ``_entry_centres``,
    ``_to_torch``, ``budget_bytes``, ``step_budget_bytes``, ``cache_dtype``, ``min_feature_mm``)."""

    def _uses_focal(self, key, pilot=None) -> bool:
        """Whether entry ``key`` propagates by the focal method: the module's ``method``, or for "auto"
        the choice :class:`rwwarp.psf.RayWave` makes for the entry's nodes (the band-limited ASM while its
        plan is small, else focal), recorded in :attr:`plans`. ``pilot``: the entry's (:meth:`_pilot`) or None.

        Under "auto" a learning DOE with a fabrication limit (``min_feature_mm``) takes the ASM: its entry is
        planned once for every DOE within the limit (:meth:`_auto_plan`) and never rebuilt, while a focal plan
        follows the current DOE's diffraction orders and windows and grows as the DOE develops (a489_aberration
        gpu preset: orders -31..33 of the 16-level relief at the limit, 10x the memory; on an H200 the e2e_doe
        step went from 20 to 117 GB and 0.9 to 4.3 s within 20 steps: perf/results/session19_h200x4/)."""
        m = self.module.method
        if m not in PLANNER_CHOICES:   # "two-step": auto's choice, with the wave step (_build, _build_focal)
            return get_method(m).torch_path == "focal"
        rec = self.plans.get(key) or {}
        if rec.get("method") in names():
            return get_method(rec["method"]).torch_path == "focal"
        if self.min_feature_mm is not None and self.module.doe_index.numel() > 0:
            return False
        from rwwarp.psf import RayWave
        geo, fields, depth = self._geometry(key[1])
        probe = RayWave(geo.to_lens(), fields, [float(key[0])] * len(fields), self.size, self.pixel_mm,
                        device=geo.rw_device, plan=geo.plan_policy, amplitude=geo.amplitude, object_distance_mm=depth,
                        rays_per_sample=geo.rays_per_sample, use_reference=geo.use_reference,
                        gauss_nodes=geo.gauss_nodes, nyquist_safety=geo.nyquist_safety, method="auto",
                        focal_patch_tol=geo.focal_patch_tol, pixel_values=geo.pixel_values, auto_rule="small-asm",
                        pilot=pilot)
        return get_method(probe.plan.method).torch_path == "focal"

    def _pilot(self, geo, fields, wavelength_um, depth):
        """The pilot of an entry's nodes ``fields`` (deg) at ``wavelength_um`` (um) from ``geo``'s current lens,
        object at ``depth`` (mm, None: the lens's), in one trace (:func:`rwwarp.wave.pilot.trace_pilot`): every
        RayWave of the entry is planned from its rows (:meth:`~rwwarp.wave.pilot.Pilot.subset`), the same bits
        as the pilot each would trace itself (rays are independent; one wavelength: one entrance pupil)."""
        from rwwarp.psf import trace_pilot
        return trace_pilot(geo.to_lens(), fields, [float(wavelength_um)] * len(fields), geo.rw_device,
                           object_distance_mm=depth, use_reference=geo.use_reference)

    def _build_focal(self, key, centres=None, pilot=None):
        """Cache one entry for the focal method: each node its own RayWave (its own focal plan: grids follow
        that node's patch and the DOE orders reaching it; from its rows of the entry's ``pilot``, traced here if
        None) and wave-plane field, traced without gradients."""
        wavelength_um, depth_mm = key
        geo, fields, depth = self._geometry(depth_mm)
        pilot = self._pilot(geo, fields, wavelength_um, depth) if pilot is None else pilot
        centres = self._entry_centres(key, centres, geo, fields, depth)
        dev = self.module.thickness_base.device
        budget = self.budget_bytes()
        nodes, log = [], []
        for k, f in enumerate(fields):
            rw = geo.raywave([f], [float(wavelength_um)], self.size, object_distance_mm=depth, pixel_mm=self.pixel_mm,
                             center_mm=centres[k:k + 1], requires_grad=False, method="focal",
                             memory_budget_bytes=budget, pilot=pilot.subset([k]))
            if self.module.method == "two-step":   # the node's focal plan with its wave step (the live path's)
                add_wave_step(rw, budget)
            # the wave step does not depend on the DOE behind it: the field is cached after it
            u = self._to_torch(rw.wave_stepped(rw.field_array()), dev, self.cache_dtype)
            nodes.append((rw, u, torch.as_tensor(rw.entering, dtype=torch.float64, device=dev)))
            log.append({"n_grid": rw.plan.n_grid, "n_sensor": rw.plan.n_sensor, "ray_grid": rw.plan.ray_grid,
                        "orders": [m for m, _ in rw.focal["orders"][0]],
                        "estimate_bytes": rw.plan.estimate["memory_bytes"]})
        if str(geo.rw_device).startswith("cuda"):
            from rwwarp.trace import release_warp_pool
            release_warp_pool(geo.rw_device)
        rw0 = nodes[0][0]
        dist = float(rw0.z_sensor - rw0.z_plane)
        self.build_log.append({"key": list(key), "method": "focal", "nsrc": len(nodes), "nodes": log})
        self._focal[key] = (nodes, dist, geo)
        self.plans[key] = {"method": "focal", "centers": centres.tolist(), "safety": float(geo.nyquist_safety),
                           "n_grid": [e["n_grid"] for e in log]}
        return self._focal[key]

    #: estimated bytes of one focal node's autograd graph (:func:`torch_bridge.budget.focal_graph_bytes`)
    focal_graph_bytes = staticmethod(focal_graph_bytes)

    def _focal_psfs(self, key, entry, doe, thick, budget_bytes: int | None = None):
        """(n_nodes, size, size) for a focal entry: DOE orders of the current DOE applied to each node's
        cached field, focal propagation (each node a checkpoint when a gradient is wanted, there is more
        than one node and their graphs together exceed ``budget_bytes``, this entry's share of the step's
        memory budget; default :meth:`step_budget_bytes`)."""
        from torch_bridge.functions import focal_doe_factor, focal_propagate
        from torch_bridge.tiles import run_tiles, wants_grad
        nodes, dist, geo = entry
        ts = [doe] if thick is None else [doe, thick]
        wants = wants_grad(ts)
        # a node's graph holds a few wave-plane arrays per kept DOE order and its output nodes (the fields
        # are cached, nothing is traced): checkpoint (recompute in backward) when all nodes' graphs together
        # would not fit this entry's share of the budget (the graphs of every entry of a call live at once,
        # beside the network's activations)
        share = self.step_budget_bytes() if budget_bytes is None else int(budget_bytes)
        # a complex64 cache adds the complex128 copy of each node's field the graph holds
        upcast = 16 if self.cache_dtype != torch.complex128 else 0
        graph = sum(self.focal_graph_bytes(rw) + upcast * rw.plan.n_grid ** 2 for rw, _, _ in nodes)
        checkpoint = len(nodes) > 1 and wants and graph > share
        # the distance's value on the host once per call (a read waits for the device), not once per node
        d_host = float(dist) if thick is None else float(thick.detach())
        def run(node, doe_t, thick_t=None, record=True):
            rw, u, entering = node
            ctx = torch.enable_grad() if record else torch.no_grad()
            with ctx:
                d = torch.full((1,), dist, dtype=torch.float64, device=u.device) if thick_t is None \
                    else thick_t.reshape(1)
                v = u.to(torch.complex128)
                fac = focal_doe_factor(rw, geo.doe_phase(rw, {"doe": doe_t}, wrap=False))
                if fac is not None:
                    v = v * fac
                return focal_propagate(v, d, rw, d_host) / entering[:, None, None]
        out = run_tiles(nodes, run, ts, checkpoint=checkpoint)   # one node a tile (torch_bridge.tiles)
        self.step_log.append({"key": list(key), "method": "focal", "chunk": 1, "chunks": len(nodes),
                              "checkpoint": bool(checkpoint), "graph_bytes_estimate": int(graph),
                              "budget_share_bytes": int(share)})
        del self.step_log[:-64]
        return out

    def _check_focal(self, current) -> int:
        """:meth:`check_sampling` for focal entries: each node is planned again from the current lens (a
        pilot trace); the entry is rebuilt when a node now needs a finer wave-plane pitch, a wider
        wave-plane window or sensor-side box (by more than 2 %), or DOE orders it did not compute, or when
        its patch centre moved by more than ``size / 8`` pixels."""
        from rwwarp.psf import RayWave
        rebuilt = 0
        for key in list(self._focal):
            nodes, _, geo = self._focal[key]
            geo_now, cen = current(key[1])
            _, fields, depth = self._geometry(key[1])
            lens = geo_now.to_lens()
            why = pilot = None
            for k, (rw, _, _) in enumerate(nodes):
                if np.max(np.abs(cen[k] - rw.centers[0])) > self.size * self.pixel_mm / 8.0:
                    why = {"reason": "re-centre", "shift_um": float(np.max(np.abs(cen[k] - rw.centers[0]))) * 1e3}
                    break
                pilot = self._pilot(geo_now, fields, key[0], depth) if pilot is None else pilot   # one for all nodes
                new = RayWave(lens, [fields[k]], [float(key[0])], self.size, self.pixel_mm, device=geo_now.rw_device,
                              plan=geo_now.plan_policy, amplitude=geo_now.amplitude, object_distance_mm=depth,
                              rays_per_sample=geo_now.rays_per_sample, center_mm=rw.centers,
                              use_reference=geo_now.use_reference, gauss_nodes=rw.gauss_nodes,
                              nyquist_safety=geo_now.nyquist_safety, method="focal",
                              focal_patch_tol=geo_now.focal_patch_tol, pixel_values=geo_now.pixel_values,
                              pilot=pilot.subset([k]))
                if self.module.method == "two-step":   # compared with the cached node's plan, step included
                    add_wave_step(new)
                a, b = rw.plan, new.plan
                orders_old = {m for m, _ in rw.focal["orders"][0]}
                orders_new = {m for m, _ in new.focal["orders"][0]}
                if (b.pitch_mm < 0.98 * a.pitch_mm or b.n_grid * b.pitch_mm > 1.02 * a.n_grid * a.pitch_mm
                        or b.n_sensor * b.sensor_pitch_mm > 1.02 * a.n_sensor * a.sensor_pitch_mm
                        or not orders_new <= orders_old):
                    why = {"reason": "sampling", "node": k, "pitch_um": [a.pitch_mm * 1e3, b.pitch_mm * 1e3],
                           "orders": sorted(orders_new - orders_old)}
                    break
            if why is not None:
                self.replan_log.append({"key": list(key), "method": "focal", **why})
                self._focal.pop(key)
                self.plans.pop(key, None)
                self._build_focal(key, cen if why["reason"] == "re-centre" else None)
                rebuilt += 1
        return rebuilt
