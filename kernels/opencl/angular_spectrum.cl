/* angular_spectrum.cl: band-limited angular spectrum propagation (Matsushima & Shimobaba 2009; shifted
 * form, Matsushima 2010) with the output evaluated at arbitrary sensor coordinates by a separable
 * matrix DFT, sensor-pixel box integration, and the adjoints of all of these.
 * Host side: rwwarp/propagate.py (launch sequencing), rwwarp/backend.py (build, FFTs).
 *
 * Index order and conventions
 *   Arrays are C-ordered (batch b, row j = y, column i = x); a complex number is (x = re, y = im).
 *   Input sample (row j, col i) of batch element b sits at
 *       x = x0[b] + i * dx[b],  y = y0[b] + j * dy[b]          (mm)
 *   It is copied to the same (j, i) of the zero-padded (npy, npx) array, so the padded grid starts
 *   at (x0, y0) too. FFT column i_f <-> grid frequency fx = q / (npx * dx) (cycles/mm), q the signed
 *   index (i_f or i_f - npx). The field may carry a factored-out carrier (cx, cy) (cycles/mm): the
 *   true field is u(x, y) exp(2 pi i (cx x + cy y)), so the true spatial frequency of grid
 *   frequency fx is u = fx + cx.
 *
 * Equations
 *   Transfer function (evanescent waves -> 0), with w = sqrt(1/lambda^2 - u^2 - v^2):
 *       H(u, v) = exp(2 pi i z w) * exp(2 pi i (fx xs + fy ys)) * scale       if inside the band
 *   formed as exp(2 pi i (frac(z/lambda) + z (w - 1/lambda) + fx xs + fy ys)) with
 *   w - 1/lambda = -lambda rho^2 / (1 + sqrt(1 - lambda^2 rho^2)) (no cancellation).
 *   (xs, ys) is the shift of the output window centre from the input window centre (shifted ASM).
 *   Band (Matsushima): u in [u_lo, u_hi], v in [v_lo, v_hi] (computed on the host, see
 *   rwwarp/propagate.py), stored compactly: band column kx <-> signed grid index q = qx0 + kx.
 *   Arbitrary-point path: the 2-D FFT is pruned: x-FFT of the ny non-zero rows only, then the
 *   y-FFT of the band columns only (column_gather), then band_gather multiplies by H.
 *   Output field at (x, y) (matrix DFT, exact trigonometric interpolation of the band-limited
 *   result), with the carrier restored:
 *       U(x, y) = sum_{ky, kx} Ey[y, ky] C[ky, kx] Ex[x, kx]
 *       Ex[x, kx] = exp(2 pi i (fx (x - x0 - xs) + cx x)),  Ey likewise,
 *       C = H * FFT(padded field) restricted to the band (H carries 1 / (npx npy)).
 *   Sensor: I[py, px] = (pitch_x pitch_y / 4) sum_{gy, gx} w_gy w_gx |U(node)|^2 (Gauss-Legendre),
 *   or the z-flux (pixel_values "flux"): the same sum of Re(conj(U) U_w), U_w the matrix DFT of c C with the
 *   direction cosine c = lambda w = k_z / k = sqrt(1 - lambda^2 (u^2 + v^2)) (band_obliquity), so that
 *   Re(conj(U) U_w) = Re(conj(U) dU/dz / (i k)), the z-component of the Poynting vector (scalar field).
 *
 * Units: mm for lengths, cycles/mm for frequencies, radians for DOE phases.
 * Kernel arguments run inputs, scalars, then outputs (named *_out).
 */
#include "complex.h"

/* Per-batch parameter row (phase_t[NPAR]); mirrored by rwwarp/propagate.py (_P_* constants). */
#define P_LAMBDA 0    /* wavelength, mm */
#define P_Z 1         /* propagation distance, mm */
#define P_ZFRAC 2     /* z / lambda - rint(z / lambda), cycles */
#define P_LPX 3       /* padded window width npx * dx, mm */
#define P_LPY 4
#define P_X0 5        /* x of input / padded sample (j, i) = (0, 0), mm */
#define P_Y0 6
#define P_XS 7        /* output window centre - input window centre, mm */
#define P_YS 8
#define P_CX 9        /* carrier factored out of the field, cycles/mm */
#define P_CY 10
#define P_ULO 11      /* band limits on the true frequency, cycles/mm */
#define P_UHI 12
#define P_VLO 13
#define P_VHI 14
#define P_QX0 15      /* signed grid-frequency index of band column 0 */
#define P_QY0 16
#define P_KXB 17      /* number of band columns used by this batch element (<= kx_max) */
#define P_KYB 18
#define P_DOE_SCALE 19 /* DOE phase multiplier (n_lambda - 1)/(n0 - 1) * lambda0/lambda */
#define NPAR 20

RW_FUNC int rw_wrap(const int i, const int n)
{
    const int r = i % n;
    return r < 0 ? r + n : r;
}

/* Field times exp(i doe_scale[b] phi) into the top-left (ny, nx) corner of a zeroed (npy, npx)
 * array. Global work size: (npx, npy, batch). */
__kernel void pad_modulate_kernel(__global const cplx_t* restrict field,
                                  __global const real_t* restrict doe_phase,
                                  __global const phase_t* restrict params,
                                  const int nx, const int ny, const int npx, const int npy,
                                  const int batch, const int has_phase, const int phase_batched,
                                  __global cplx_t* restrict padded_out)
{
    const int ix = get_global_id(0);
    const int iy = get_global_id(1);
    const int b = get_global_id(2);
    if (ix >= npx || iy >= npy || b >= batch) return;
    cplx_t v = c_zero();
    if (ix < nx && iy < ny) {
        v = field[((idx_t)b * ny + iy) * nx + ix];
        if (has_phase) {
            const idx_t ip = ((idx_t)(phase_batched ? b : 0) * ny + iy) * nx + ix;
            v = c_mul(v, c_expi(params[b * NPAR + P_DOE_SCALE] * (phase_t)doe_phase[ip]));
        }
    }
    padded_out[((idx_t)b * npy + iy) * npx + ix] = v;
}

/* Transfer function on the compact band grid, (batch, ky_max, kx_max). Global (kx_max, ky_max, batch). */
__kernel void band_transfer_kernel(__global const phase_t* restrict params,
                                   const int kx_max, const int ky_max, const int batch,
                                   const real_t scale,
                                   __global cplx_t* restrict h_out)
{
    const int kx = get_global_id(0);
    const int ky = get_global_id(1);
    const int b = get_global_id(2);
    if (kx >= kx_max || ky >= ky_max || b >= batch) return;
    __global const phase_t* p = params + (idx_t)b * NPAR;
    cplx_t h = c_zero();
    if (kx < (int)p[P_KXB] && ky < (int)p[P_KYB]) {
        const phase_t fx = (p[P_QX0] + (phase_t)kx) / p[P_LPX];
        const phase_t fy = (p[P_QY0] + (phase_t)ky) / p[P_LPY];
        const phase_t u = fx + p[P_CX];
        const phase_t v = fy + p[P_CY];
        if (u >= p[P_ULO] && u <= p[P_UHI] && v >= p[P_VLO] && v <= p[P_VHI]) {
            const phase_t lam = p[P_LAMBDA];
            const phase_t rho2 = u * u + v * v;
            const phase_t s2 = lam * lam * rho2;
            if (s2 < (phase_t)1) {
                const phase_t dw = -lam * rho2 / ((phase_t)1 + sqrt((phase_t)1 - s2));
                const phase_t cyc_z = p[P_ZFRAC] + p[P_Z] * dw;
                const phase_t cyc_s = fx * p[P_XS] + fy * p[P_YS];
                h = c_scale(c_cis_cycles(rw_frac_nearest(cyc_z) + rw_frac_nearest(cyc_s)), scale);
            }
        }
    }
    h_out[((idx_t)b * ky_max + ky) * kx_max + kx] = h;
}

/* Pruned 2-D FFT, step 2: after the x-FFT of the (ny, npx) rows, keep the band columns and
 * zero-pad them to npy rows: cols_out[b, iy, kx] = rows[b, iy, qx0 + kx (mod npx)] for iy < ny, else
 * 0. The y-FFT of cols_out then gives the padded field's spectrum on the band columns.
 * Global (kx_max, npy, batch). */
__kernel void column_gather_kernel(__global const cplx_t* restrict rows,
                                   __global const phase_t* restrict params,
                                   const int ny, const int npx, const int npy, const int kx_max,
                                   const int batch,
                                   __global cplx_t* restrict cols_out)
{
    const int kx = get_global_id(0);
    const int iy = get_global_id(1);
    const int b = get_global_id(2);
    if (kx >= kx_max || iy >= npy || b >= batch) return;
    cplx_t v = c_zero();
    if (iy < ny) {
        const int ix = rw_wrap((int)params[(idx_t)b * NPAR + P_QX0] + kx, npx);
        v = rows[((idx_t)b * ny + iy) * npx + ix];
    }
    cols_out[((idx_t)b * npy + iy) * kx_max + kx] = v;
}

/* Adjoint of column_gather (rows of the padded grid beyond ny are dropped: they are cropped
 * anyway): rows_out[b, iy, ix] = cols[b, iy, kx] with kx = ix - qx0 (mod npx) if kx < kx_max,
 * else 0. Global (npx, ny, batch). */
__kernel void column_scatter_adjoint_kernel(__global const cplx_t* restrict cols,
                                            __global const phase_t* restrict params,
                                            const int ny, const int npx, const int npy,
                                            const int kx_max, const int batch,
                                            __global cplx_t* restrict rows_out)
{
    const int ix = get_global_id(0);
    const int iy = get_global_id(1);
    const int b = get_global_id(2);
    if (ix >= npx || iy >= ny || b >= batch) return;
    const int kx = rw_wrap(ix - (int)params[(idx_t)b * NPAR + P_QX0], npx);
    cplx_t v = c_zero();
    if (kx < kx_max) v = cols[((idx_t)b * npy + iy) * kx_max + kx];
    rows_out[((idx_t)b * ny + iy) * npx + ix] = v;
}

/* band_out = H * spectrum on the band, from the band-column spectrum cols (batch, npy, kx_max)
 * (column kx = grid column qx0 + kx, all npy rows). Global (kx_max, ky_max, batch). */
__kernel void band_gather_kernel(__global const cplx_t* restrict cols,
                                 __global const cplx_t* restrict h,
                                 __global const phase_t* restrict params,
                                 const int npy, const int kx_max, const int ky_max, const int batch,
                                 __global cplx_t* restrict band_out)
{
    const int kx = get_global_id(0);
    const int ky = get_global_id(1);
    const int b = get_global_id(2);
    if (kx >= kx_max || ky >= ky_max || b >= batch) return;
    const int iy = rw_wrap((int)params[(idx_t)b * NPAR + P_QY0] + ky, npy);
    const idx_t ib = ((idx_t)b * ky_max + ky) * kx_max + kx;
    band_out[ib] = c_mul(cols[((idx_t)b * npy + iy) * kx_max + kx], h[ib]);
}

/* Gradient of a real loss with respect to the propagation distance z, through the band spectrum
 * C = H * FFT(field) (band_gather's output). H depends on z through exp(2 pi i z w),
 * w = sqrt(1/lambda^2 - u^2 - v^2) (cycles/mm), so dC/dz = 2 pi i w C and, for
 * G = dL/dRe C + i dL/dIm C (the gradient of the band, from the adjoint of the matrix DFT),
 *     dL/dz = Re sum conj(G) dC/dz = 2 pi sum w (Im G Re C - Re G Im C).
 * full_w = 0 uses w - 1/lambda = -lambda rho^2 / (1 + sqrt(1 - lambda^2 rho^2)) instead of w: it
 * drops the z-derivative of the global phase exp(2 pi i z / lambda), which intensities do not see
 * (and which would otherwise be summed to ~0 from terms 1/(lambda |w - 1/lambda|) times larger).
 * The band limits also move with z; their jumps are not differentiated (zero a.e.).
 * out[b, ky] = partial sum over kx (phase_t, 1/mm units of the loss); the host sums over ky.
 * Global (ky_max, batch, 1). */
__kernel void band_distance_grad_kernel(__global const cplx_t* restrict band,
                                        __global const cplx_t* restrict band_grad,
                                        __global const phase_t* restrict params,
                                        const int kx_max, const int ky_max, const int batch,
                                        const int full_w,
                                        __global phase_t* restrict out)
{
    const int ky = get_global_id(0);
    const int b = get_global_id(1);
    if (ky >= ky_max || b >= batch) return;
    __global const phase_t* p = params + (idx_t)b * NPAR;
    phase_t acc = (phase_t)0;
    if (ky < (int)p[P_KYB]) {
        const phase_t lam = p[P_LAMBDA];
        const phase_t v = (p[P_QY0] + (phase_t)ky) / p[P_LPY] + p[P_CY];
        const int kxb = (int)p[P_KXB];
        const idx_t row = ((idx_t)b * ky_max + ky) * kx_max;
        for (int kx = 0; kx < kxb && kx < kx_max; ++kx) {
            const phase_t u = (p[P_QX0] + (phase_t)kx) / p[P_LPX] + p[P_CX];
            const phase_t rho2 = u * u + v * v;
            const phase_t s2 = lam * lam * rho2;
            if (s2 < (phase_t)1) {
                const phase_t dw = -lam * rho2 / ((phase_t)1 + sqrt((phase_t)1 - s2));
                const phase_t w = full_w ? dw + (phase_t)1 / lam : dw;
                const cplx_t g = band_grad[row + kx];
                const cplx_t c = band[row + kx];
                acc += w * ((phase_t)g.y * (phase_t)c.x - (phase_t)g.x * (phase_t)c.y);
            }
        }
    }
    out[(idx_t)b * ky_max + ky] = RW_TWO_PI * acc;
}

/* Direction-cosine weight on the band (pixel_values "flux"): out = c^power src (+ out when accumulate),
 * c = lambda w = sqrt(1 - lambda^2 (u^2 + v^2)) = k_z / k, the cosine of the plane wave's angle to z (lambda in
 * the medium); 0 outside the band and for evanescent (u, v), where C is 0 too. The weight is real, so the same
 * launch is its own adjoint. minus_one (power >= 1): the weight c^(power-1) (c - 1) instead, c - 1 formed as
 * -lambda^2 rho^2 / (1 + c) (no cancellation near the axis: the distance derivative without the constant phase
 * 2 pi z / lambda). Global (kx_max, ky_max, batch). */
__kernel void band_obliquity_kernel(__global const cplx_t* restrict src,
                                    __global const phase_t* restrict params,
                                    const int kx_max, const int ky_max, const int batch,
                                    const int power, const int accumulate, const int minus_one,
                                    __global cplx_t* restrict band_out)
{
    const int kx = get_global_id(0);
    const int ky = get_global_id(1);
    const int b = get_global_id(2);
    if (kx >= kx_max || ky >= ky_max || b >= batch) return;
    __global const phase_t* p = params + (idx_t)b * NPAR;
    const idx_t ib = ((idx_t)b * ky_max + ky) * kx_max + kx;
    phase_t wgt = (phase_t)0;
    if (kx < (int)p[P_KXB] && ky < (int)p[P_KYB]) {
        const phase_t u = (p[P_QX0] + (phase_t)kx) / p[P_LPX] + p[P_CX];
        const phase_t v = (p[P_QY0] + (phase_t)ky) / p[P_LPY] + p[P_CY];
        const phase_t lam = p[P_LAMBDA];
        const phase_t s2 = lam * lam * (u * u + v * v);
        if (s2 < (phase_t)1) {
            const phase_t c = sqrt((phase_t)1 - s2);
            wgt = (phase_t)1;
            const int np_ = minus_one ? power - 1 : power;
            for (int k = 0; k < (np_ < 0 ? -np_ : np_); ++k) wgt *= c;
            if (np_ < 0) wgt = (phase_t)1 / wgt;
            if (minus_one) wgt *= -s2 / ((phase_t)1 + c);
        }
    }
    cplx_t v = c_scale(src[ib], (real_t)wgt);
    if (accumulate) v = c_add(v, band_out[ib]);
    band_out[ib] = v;
}

/* Adjoint of band_gather: cols_out = scale * conj(H) * band on the band rows, 0 on the other
 * rows, laid out as (batch, npy, kx_max). Global (kx_max, npy, batch). */
__kernel void band_scatter_adjoint_kernel(__global const cplx_t* restrict band,
                                          __global const cplx_t* restrict h,
                                          __global const phase_t* restrict params,
                                          const int npy, const int kx_max, const int ky_max,
                                          const int batch, const real_t scale,
                                          __global cplx_t* restrict cols_out)
{
    const int kx = get_global_id(0);
    const int iy = get_global_id(1);
    const int b = get_global_id(2);
    if (kx >= kx_max || iy >= npy || b >= batch) return;
    const int ky = rw_wrap(iy - (int)params[(idx_t)b * NPAR + P_QY0], npy);
    cplx_t v = c_zero();
    if (ky < ky_max) {
        const idx_t ib = ((idx_t)b * ky_max + ky) * kx_max + kx;
        v = c_scale(c_conj_mul(h[ib], band[ib]), scale);
    }
    cols_out[((idx_t)b * npy + iy) * kx_max + kx] = v;
}

/* In-place spectrum *= H (or conj(H)) on the band, 0 elsewhere (fixed-grid path and its adjoint).
 * Global (npx, npy, batch). */
__kernel void spectrum_multiply_kernel(__global const cplx_t* restrict h,
                                       __global const phase_t* restrict params,
                                       const int npx, const int npy, const int kx_max,
                                       const int ky_max, const int batch, const int conj_h,
                                       __global cplx_t* restrict spectrum_inout)
{
    const int ix = get_global_id(0);
    const int iy = get_global_id(1);
    const int b = get_global_id(2);
    if (ix >= npx || iy >= npy || b >= batch) return;
    __global const phase_t* p = params + (idx_t)b * NPAR;
    const int kx = rw_wrap(ix - (int)p[P_QX0], npx);
    const int ky = rw_wrap(iy - (int)p[P_QY0], npy);
    const idx_t is = ((idx_t)b * npy + iy) * npx + ix;
    cplx_t v = c_zero();
    if (kx < kx_max && ky < ky_max) {
        const cplx_t hv = h[((idx_t)b * ky_max + ky) * kx_max + kx];
        v = c_mul(conj_h ? c_conj(hv) : hv, spectrum_inout[is]);
    }
    spectrum_inout[is] = v;
}

/* Matrix-DFT factor of one axis (axis 0 = x, 1 = y):
 *     E[n, k] = exp(2 pi i (f_k (s_n - s0 - shift) + c s_n)),  f_k = (q0 + k) / Lp, 0 for k >= K_b,
 * s_n = coords[b, n] (mm). transpose = 0 stores (batch, m_count, k_max) [Ey, left factor],
 * transpose = 1 stores (batch, k_max, m_count) [Ex^T, right factor].
 * Global: (k_max, m_count, batch) if transpose = 0, (m_count, k_max, batch) if transpose = 1. */
__kernel void dft_matrix_kernel(__global const phase_t* restrict coords,
                                __global const phase_t* restrict params,
                                const int m_count, const int k_max, const int batch, const int axis,
                                const int transpose,
                                __global cplx_t* restrict e_out)
{
    const int g0 = get_global_id(0);
    const int g1 = get_global_id(1);
    const int b = get_global_id(2);
    const int k = transpose ? g1 : g0;
    const int n = transpose ? g0 : g1;
    if (k >= k_max || n >= m_count || b >= batch) return;
    __global const phase_t* p = params + (idx_t)b * NPAR;
    cplx_t e = c_zero();
    if (k < (int)p[P_KXB + axis]) {
        const phase_t s = coords[(idx_t)b * m_count + n];
        const phase_t f = (p[P_QX0 + axis] + (phase_t)k) / p[P_LPX + axis];
        const phase_t t1 = f * (s - p[P_X0 + axis] - p[P_XS + axis]);
        const phase_t t2 = p[P_CX + axis] * s;
        e = c_cis_cycles(rw_frac_nearest(t1) + rw_frac_nearest(t2));
    }
    const idx_t io = transpose ? ((idx_t)b * k_max + k) * m_count + n
                               : ((idx_t)b * m_count + n) * k_max + k;
    e_out[io] = e;
}

/* Batched complex matrix product c_out[b] = op(A[b]) op(B[b]), op = optional transpose and/or
 * conjugate; op(A) is m x k, op(B) is k x n, all row-major with leading dimensions lda/ldb/ldc
 * (elements) and batch strides stride_* (elements; 0 broadcasts one matrix over the batch).
 * Tiled through local memory: a GEMM_TS x GEMM_TS output tile per work-group of
 * GEMM_WG x GEMM_WG work-items, each computing GEMM_WPT x GEMM_WPT outputs.
 * Global (ceil(n / GEMM_TS) * GEMM_WG, ceil(m / GEMM_TS) * GEMM_WG, batch), local (GEMM_WG, GEMM_WG, 1). */
#ifndef GEMM_TS
#define GEMM_TS 32
#endif
#ifndef GEMM_TK
#define GEMM_TK 16
#endif
#ifndef GEMM_WG
#define GEMM_WG 16
#endif
#define GEMM_WPT (GEMM_TS / GEMM_WG)

__kernel void cgemm_batched_kernel(__global const cplx_t* restrict a,
                                   __global const cplx_t* restrict bmat,
                                   const int m, const int n, const int k,
                                   const int lda, const int ldb, const int ldc,
                                   const idx_t stride_a, const idx_t stride_b, const idx_t stride_c,
                                   const int trans_a, const int conj_a,
                                   const int trans_b, const int conj_b,
                                   __global cplx_t* restrict c_out)
{
    __local cplx_t a_tile[GEMM_TK][GEMM_TS];
    __local cplx_t b_tile[GEMM_TK][GEMM_TS];
    const int tx = get_local_id(0);
    const int ty = get_local_id(1);
    const int tid = ty * GEMM_WG + tx;
    const int col0 = get_group_id(0) * GEMM_TS;
    const int row0 = get_group_id(1) * GEMM_TS;
    const idx_t bi = get_group_id(2);
    __global const cplx_t* ab = a + bi * stride_a;
    __global const cplx_t* bb = bmat + bi * stride_b;

    cplx_t acc[GEMM_WPT][GEMM_WPT];
    for (int wi = 0; wi < GEMM_WPT; ++wi)
        for (int wj = 0; wj < GEMM_WPT; ++wj) acc[wi][wj] = c_zero();

    for (int k0 = 0; k0 < k; k0 += GEMM_TK) {
        for (int e = tid; e < GEMM_TS * GEMM_TK; e += GEMM_WG * GEMM_WG) {
            int ii, kk;
            if (trans_a) { kk = e / GEMM_TS; ii = e % GEMM_TS; }
            else { ii = e / GEMM_TK; kk = e % GEMM_TK; }
            const int gi = row0 + ii;
            const int gk = k0 + kk;
            cplx_t v = c_zero();
            if (gi < m && gk < k) v = trans_a ? ab[(idx_t)gk * lda + gi] : ab[(idx_t)gi * lda + gk];
            if (conj_a) v.y = -v.y;
            a_tile[kk][ii] = v;
        }
        for (int e = tid; e < GEMM_TS * GEMM_TK; e += GEMM_WG * GEMM_WG) {
            int jj, kk;
            if (trans_b) { jj = e / GEMM_TK; kk = e % GEMM_TK; }
            else { kk = e / GEMM_TS; jj = e % GEMM_TS; }
            const int gj = col0 + jj;
            const int gk = k0 + kk;
            cplx_t v = c_zero();
            if (gj < n && gk < k) v = trans_b ? bb[(idx_t)gj * ldb + gk] : bb[(idx_t)gk * ldb + gj];
            if (conj_b) v.y = -v.y;
            b_tile[kk][jj] = v;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int kk = 0; kk < GEMM_TK; ++kk) {
            cplx_t av[GEMM_WPT], bv[GEMM_WPT];
            for (int w = 0; w < GEMM_WPT; ++w) {
                av[w] = a_tile[kk][ty + w * GEMM_WG];
                bv[w] = b_tile[kk][tx + w * GEMM_WG];
            }
            for (int wi = 0; wi < GEMM_WPT; ++wi)
                for (int wj = 0; wj < GEMM_WPT; ++wj) acc[wi][wj] = c_mad(av[wi], bv[wj], acc[wi][wj]);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    __global cplx_t* cb = c_out + bi * stride_c;
    for (int wi = 0; wi < GEMM_WPT; ++wi) {
        const int row = row0 + ty + wi * GEMM_WG;
        for (int wj = 0; wj < GEMM_WPT; ++wj) {
            const int col = col0 + tx + wj * GEMM_WG;
            if (row < m && col < n) cb[(idx_t)row * ldc + col] = acc[wi][wj];
        }
    }
}

#ifndef RW_CUDA
/* CPU variant of cgemm_batched_kernel (same arguments and result; OpenCL only, chosen by the host
 * for CPU devices such as PoCL). CPU OpenCL runs each work-item's loop as scalar code, so this
 * kernel vectorises explicitly: a work-item owns CGEMM_CPU_ROWS rows x 4 columns of the output,
 * held as real4 vectors of real and imaginary parts, and streams over k with no local memory
 * and no barriers. op(B) must not be transposed (trans_b = 0; conj_b is honoured).
 * Global (ceil(n / 4), ceil(m / CGEMM_CPU_ROWS), batch), any local size along axis 0. */
#define CGEMM_CPU_ROWS 8
#if REAL_IS_DOUBLE
typedef double2 rw_real2_t;
typedef double4 rw_real4_t;
#else
typedef float2 rw_real2_t;
typedef float4 rw_real4_t;
#endif

__kernel void cgemm_cpu_kernel(__global const cplx_t* restrict a,
                               __global const cplx_t* restrict bmat,
                               const int m, const int n, const int k,
                               const int lda, const int ldb, const int ldc,
                               const idx_t stride_a, const idx_t stride_b, const idx_t stride_c,
                               const int trans_a, const int conj_a,
                               const int trans_b, const int conj_b,
                               __global cplx_t* restrict c_out)
{
    const int j0 = get_global_id(0) * 4;
    const int i0 = get_global_id(1) * CGEMM_CPU_ROWS;
    const idx_t bi = get_global_id(2);
    if (j0 >= n || i0 >= m) return;
    __global const cplx_t* ab = a + bi * stride_a;
    __global const real_t* bb = (__global const real_t*)(bmat + bi * stride_b);
    const idx_t a_si = trans_a ? 1 : lda;
    const idx_t a_sk = trans_a ? lda : 1;
    const real_t sign_a = conj_a ? (real_t)-1 : (real_t)1;
    const real_t sign_b = conj_b ? (real_t)-1 : (real_t)1;
    const int full = (j0 + 4 <= n);
    const int rows = min(m - i0, CGEMM_CPU_ROWS);
    int arow[CGEMM_CPU_ROWS];
    rw_real4_t acc_re[CGEMM_CPU_ROWS], acc_im[CGEMM_CPU_ROWS];
    for (int r = 0; r < CGEMM_CPU_ROWS; ++r) {
        arow[r] = r < rows ? r : 0;
        acc_re[r] = (rw_real4_t)(0);
        acc_im[r] = (rw_real4_t)(0);
    }
    for (int kk = 0; kk < k; ++kk) {
        __global const real_t* bp = bb + 2 * ((idx_t)kk * ldb + j0);
        rw_real4_t b_re, b_im;
        if (full) {
            const rw_real4_t lo = vload4(0, bp);  /* re0 im0 re1 im1 */
            const rw_real4_t hi = vload4(1, bp);  /* re2 im2 re3 im3 */
            b_re = (rw_real4_t)(lo.even, hi.even);
            b_im = sign_b * (rw_real4_t)(lo.odd, hi.odd);
        } else {
            real_t re[4], im[4];
            for (int e = 0; e < 4; ++e) {
                const int ok = j0 + e < n;
                re[e] = ok ? bp[2 * e] : (real_t)0;
                im[e] = ok ? bp[2 * e + 1] : (real_t)0;
            }
            b_re = (rw_real4_t)(re[0], re[1], re[2], re[3]);
            b_im = sign_b * (rw_real4_t)(im[0], im[1], im[2], im[3]);
        }
        __global const cplx_t* ap = ab + (idx_t)i0 * a_si + (idx_t)kk * a_sk;
        for (int r = 0; r < CGEMM_CPU_ROWS; ++r) {
            const cplx_t av = ap[arow[r] * a_si];
            const rw_real4_t ar = (rw_real4_t)(av.x);
            const rw_real4_t ai = (rw_real4_t)(sign_a * av.y);
            acc_re[r] = fma(ar, b_re, fma(-ai, b_im, acc_re[r]));
            acc_im[r] = fma(ar, b_im, fma(ai, b_re, acc_im[r]));
        }
    }
    __global cplx_t* cb = c_out + bi * stride_c;
    for (int r = 0; r < rows; ++r) {
        real_t re[4], im[4];
        vstore4(acc_re[r], 0, re);
        vstore4(acc_im[r], 0, im);
        for (int e = 0; e < 4; ++e)
            if (j0 + e < n) cb[(idx_t)(i0 + r) * ldc + j0 + e] = c_make(re[e], im[e]);
    }
}
#endif /* !RW_CUDA */

/* Crop the top-left (ny, nx) corner of a (npy, npx) array. Global (nx, ny, batch). */
__kernel void crop_kernel(__global const cplx_t* restrict padded,
                          const int nx, const int ny, const int npx, const int npy, const int batch,
                          __global cplx_t* restrict field_out)
{
    const int ix = get_global_id(0);
    const int iy = get_global_id(1);
    const int b = get_global_id(2);
    if (ix >= nx || iy >= ny || b >= batch) return;
    field_out[((idx_t)b * ny + iy) * nx + ix] = padded[((idx_t)b * npy + iy) * npx + ix];
}

/* Adjoint of pad_modulate: g = the crop of padded_grad; grad_field = conj(m) g with m = exp(i s phi);
 * grad_phase = s Im(grad_field conj(field)), summed over the batch when the phase is shared.
 * Global (nx, ny, 1): each work-item loops over the batch. */
__kernel void crop_demodulate_adjoint_kernel(__global const cplx_t* restrict padded_grad,
                                             __global const cplx_t* restrict field,
                                             __global const real_t* restrict doe_phase,
                                             __global const phase_t* restrict params,
                                             const int nx, const int ny, const int npx,
                                             const int npy, const int batch, const int has_phase,
                                             const int phase_batched,
                                             __global cplx_t* restrict grad_field_out,
                                             __global real_t* restrict grad_phase_out)
{
    const int ix = get_global_id(0);
    const int iy = get_global_id(1);
    if (ix >= nx || iy >= ny) return;
    phase_t acc = (phase_t)0;
    for (int b = 0; b < batch; ++b) {
        const idx_t io = ((idx_t)b * ny + iy) * nx + ix;
        cplx_t g = padded_grad[((idx_t)b * npy + iy) * npx + ix];
        if (has_phase) {
            const idx_t ip = ((idx_t)(phase_batched ? b : 0) * ny + iy) * nx + ix;
            const phase_t s = params[(idx_t)b * NPAR + P_DOE_SCALE];
            g = c_conj_mul(c_expi(s * (phase_t)doe_phase[ip]), g);
            const cplx_t u = field[io];
            const phase_t gphi = s * ((phase_t)g.y * (phase_t)u.x - (phase_t)g.x * (phase_t)u.y);
            if (phase_batched) grad_phase_out[io] = (real_t)gphi;
            else acc += gphi;
        }
        grad_field_out[io] = g;
    }
    if (has_phase && !phase_batched) grad_phase_out[(idx_t)iy * nx + ix] = (real_t)acc;
}

/* Box integration over sensor pixels: nodes and nodes_w (batch, n_py * g, n_px * g) hold node fields at the
 * Gauss-Legendre nodes (row py * g + gy, column px * g + gx);
 * out[b, py, px] = area_scale * sum w[gy] w[gx] Re(conj(U) U_w), U = nodes, U_w = nodes_w.
 * Intensity (|U|^2): pass the same array as nodes and nodes_w. Flux (pixel_values "flux"): nodes / nodes_w the
 * node fields of C and c C; its adjoint is sensor_reduce_adjoint with area_scale / 2 on the other node field
 * (d/dU = w U_w, d/dU_w = w U in the dL/dRe + i dL/dIm convention). Global (n_px, n_py, batch). */
__kernel void sensor_reduce_kernel(__global const cplx_t* nodes,
                                   __global const cplx_t* nodes_w,
                                   __global const real_t* restrict weights,
                                   const int n_px, const int n_py, const int g, const int batch,
                                   const real_t area_scale,
                                   __global real_t* restrict out)
{
    const int px = get_global_id(0);
    const int py = get_global_id(1);
    const int b = get_global_id(2);
    if (px >= n_px || py >= n_py || b >= batch) return;
    const int row_len = n_px * g;
    real_t acc = (real_t)0;
    for (int gy = 0; gy < g; ++gy) {
        const idx_t row = ((idx_t)b * n_py * g + (idx_t)py * g + gy) * row_len + (idx_t)px * g;
        real_t acc_row = (real_t)0;
        for (int gx = 0; gx < g; ++gx) {
            const cplx_t a = nodes[row + gx];
            const cplx_t c = nodes_w[row + gx];
            acc_row += weights[gx] * (a.x * c.x + a.y * c.y);
        }
        acc += weights[gy] * acc_row;
    }
    out[((idx_t)b * n_py + py) * n_px + px] = area_scale * acc;
}

/* Adjoint of sensor_reduce for grad = dL/dRe + i dL/dIm:
 * grad_nodes_out = 2 area_scale w[gy] w[gx] grad_intensity[b, py, px] U(node).
 * Global (n_px * g, n_py * g, batch). */
__kernel void sensor_reduce_adjoint_kernel(__global const cplx_t* restrict nodes,
                                           __global const real_t* restrict weights,
                                           __global const real_t* restrict grad_intensity,
                                           const int n_px, const int n_py, const int g,
                                           const int batch, const real_t area_scale,
                                           __global cplx_t* restrict grad_nodes_out)
{
    const int cx = get_global_id(0);
    const int cy = get_global_id(1);
    const int b = get_global_id(2);
    if (cx >= n_px * g || cy >= n_py * g || b >= batch) return;
    const int px = cx / g;
    const int py = cy / g;
    const real_t f = (real_t)2 * area_scale * weights[cx - px * g] * weights[cy - py * g]
                     * grad_intensity[((idx_t)b * n_py + py) * n_px + px];
    const idx_t io = ((idx_t)b * n_py * g + cy) * (idx_t)(n_px * g) + cx;
    grad_nodes_out[io] = c_scale(nodes[io], f);
}
