/* Compiled kernels of the SLAM's hot loops, with the same arithmetic as their numpy versions
 * (named in each function's comment: proposal.align_points' Gauss-Newton, association.associate
 * and observe, update.visibility and _redundant_pairs, extraction's split and merge rounds,
 * FastSLAM._local_columns, the coarse search's and the kidnap watch's nearest samples, the scan
 * matcher's sums). The numpy code stays the reference and the fallback when this module is not
 * built; tests/slam/test_kernels.py holds both to the same results.
 *
 * Arrays come through the buffer protocol (no numpy headers at build time): C-contiguous
 * float64 unless said otherwise; the Python wrapper (robot_agent/slam/kernels.py) converts them,
 * each function here checks their sizes against the shapes it is given. Built with
 * -ffp-contract=off so that a product and a sum are not fused into one rounding the numpy code
 * does not make.
 */
#include "_common.h" /* shared/: sizes_ok, release, wrap_angle */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Piece starts rise within [0, K), else a ValueError: 1 if so. */
static int starts_ok(const char *name, const int64_t *starts, Py_ssize_t S, Py_ssize_t K) {
    for (Py_ssize_t j = 0; j < S; j++) {
        if (starts[j] < 0 || starts[j] >= K || (j > 0 && starts[j] <= starts[j - 1])) {
            PyErr_Format(PyExc_ValueError, "%s: starts must rise within [0, %zd)", name, K);
            return 0;
        }
    }
    return 1;
}

/* How far intervals [a0, a1] and [b0, b1] (ends in any order) overlap; negative: the gap
 * (lines.interval_overlap). */
static double interval_overlap(double a0, double a1, double b0, double b1) {
    double lo_a = a0 < a1 ? a0 : a1, hi_a = a0 < a1 ? a1 : a0;
    double lo_b = b0 < b1 ? b0 : b1, hi_b = b0 < b1 ? b1 : b0;
    double lo = lo_a > lo_b ? lo_a : lo_b, hi = hi_a < hi_b ? hi_a : hi_b;
    return hi - lo;
}

/* Solve the 3x3 system a x = b by Gaussian elimination with partial pivoting; 0 if singular. */
static int solve3(const double *a_in, const double *b_in, double *x) {
    double a[3][4];
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) a[i][j] = a_in[3 * i + j];
        a[i][3] = b_in[i];
    }
    for (int col = 0; col < 3; col++) {
        int piv = col;
        for (int r = col + 1; r < 3; r++)
            if (fabs(a[r][col]) > fabs(a[piv][col])) piv = r;
        if (a[piv][col] == 0.0) return 0;
        if (piv != col)
            for (int j = 0; j < 4; j++) {
                double t = a[col][j];
                a[col][j] = a[piv][j];
                a[piv][j] = t;
            }
        for (int r = col + 1; r < 3; r++) {
            double f = a[r][col] / a[col][col];
            for (int j = col; j < 4; j++) a[r][j] -= f * a[col][j];
        }
    }
    for (int i = 2; i >= 0; i--) {
        double s = a[i][3];
        for (int j = i + 1; j < 3; j++) s -= a[i][j] * x[j];
        x[i] = s / a[i][i];
    }
    return 1;
}

typedef struct {
    Py_ssize_t P, N, C;
    const double *pts;     /* (N,2) robot frame */
    const double *nx, *ny; /* (P,C) cos, sin of the element's normal angle */
    const double *rho;     /* (P,C) */
    const double *seg;     /* (P,C,2,2) */
    const double *fx, *fy; /* (P,C) cos, sin of the element's facing */
    const uint8_t *valid;  /* (P,C) */
    double margin;
    const double *pa; /* (N,) normal angle of each point's own line (robot frame), NaN: none */
    double max_sin;   /* a point pairs with an element only if |sin| of their lines' angle <= this */
    /* workspace */
    double *qx, *qy, *wx, *wy;  /* (P,N) */
    double *hc, *hs;            /* (P,) cos, sin of each particle's heading */
    double *pc, *ps;            /* (N,) cos, sin of each point's own line (NaN: none) */
    double *lo_x, *hi_x, *lo_y, *hi_y; /* (C,) the candidate boxes */
    double *ref_x, *ref_y;             /* (N,) the points' mean view */
    Py_ssize_t *cand_start; /* (N+1,) */
    Py_ssize_t *cand;       /* candidate columns, capacity cand_cap */
    Py_ssize_t cand_cap;
} Assoc;

static void rotate(Assoc *s, const double *x) {
    for (Py_ssize_t p = 0; p < s->P; p++) {
        double c = cos(x[3 * p + 2]), sn = sin(x[3 * p + 2]);
        s->hc[p] = c;
        s->hs[p] = sn;
        for (Py_ssize_t i = 0; i < s->N; i++) {
            double px = s->pts[2 * i], py = s->pts[2 * i + 1];
            double qx = c * px - sn * py + 0.0, qy = sn * px + c * py + 0.0;
            s->qx[p * s->N + i] = qx;
            s->qy[p * s->N + i] = qy;
            s->wx[p * s->N + i] = qx + x[3 * p];
            s->wy[p * s->N + i] = qy + x[3 * p + 1];
        }
    }
}

/* Element index (P,N) or -1 of every point as rotate() last placed them: see associate_points.
 * The gate is ``wide[p]`` per particle when given, else ``gate_m``. */
static int associate(Assoc *s, const double *wide, double gate_m, int64_t *idx) {
    Py_ssize_t P = s->P, N = s->N, C = s->C;
    for (Py_ssize_t k = 0; k < P * N; k++) idx[k] = -1;
    if (N == 0 || C == 0 || P == 0) return 1;
    /* the candidate pairs: the points' mean view against a box around every particle's copy of
     * each element, widened by the gate, the margin and the particles' spread (a superset) */
    double gmax = gate_m;
    if (wide) {
        gmax = wide[0];
        for (Py_ssize_t p = 1; p < P; p++)
            if (wide[p] > gmax) gmax = wide[p];
    }
    double spread = 0.0;
    double *ref_x = s->ref_x, *ref_y = s->ref_y;
    for (Py_ssize_t i = 0; i < N; i++) {
        double mx = 0.0, my = 0.0;
        for (Py_ssize_t p = 0; p < P; p++) {
            mx += s->wx[p * N + i];
            my += s->wy[p * N + i];
        }
        ref_x[i] = mx / (double)P;
        ref_y[i] = my / (double)P;
        for (Py_ssize_t p = 0; p < P; p++) {
            double dx = s->wx[p * N + i] - ref_x[i], dy = s->wy[p * N + i] - ref_y[i];
            double d2 = dx * dx + dy * dy;
            if (d2 > spread) spread = d2;
        }
    }
    spread = sqrt(spread); /* (squared above) */
    double reach = hypot(gmax, s->margin) + spread;
    /* inflate by a relative epsilon: the mean above is summed in another order than numpy's */
    reach += 1e-9 * (1.0 + reach);
    for (Py_ssize_t c = 0; c < C; c++) {
        double lx = INFINITY, hx = -INFINITY, ly = INFINITY, hy = -INFINITY;
        for (Py_ssize_t p = 0; p < P; p++) {
            if (!s->valid[p * C + c]) continue;
            const double *e = s->seg + 4 * (p * C + c);
            for (int k = 0; k < 2; k++) {
                double ex = e[2 * k], ey = e[2 * k + 1];
                if (ex < lx) lx = ex;
                if (ex > hx) hx = ex;
                if (ey < ly) ly = ey;
                if (ey > hy) hy = ey;
            }
        }
        s->lo_x[c] = lx - reach;
        s->hi_x[c] = hx + reach;
        s->lo_y[c] = ly - reach;
        s->hi_y[c] = hy + reach;
    }
    Py_ssize_t n = 0;
    for (Py_ssize_t i = 0; i < N; i++) {
        s->cand_start[i] = n;
        double rx = ref_x[i], ry = ref_y[i];
        for (Py_ssize_t c = 0; c < C; c++) {
            if (rx >= s->lo_x[c] && rx <= s->hi_x[c] && ry >= s->lo_y[c] && ry <= s->hi_y[c]) {
                if (n == s->cand_cap) {
                    Py_ssize_t cap = 2 * s->cand_cap + 64;
                    Py_ssize_t *grown = realloc(s->cand, (size_t)cap * sizeof(Py_ssize_t));
                    if (!grown) return 0;
                    s->cand = grown;
                    s->cand_cap = cap;
                }
                s->cand[n++] = c;
            }
        }
    }
    s->cand_start[N] = n;
    /* the exact test on the candidates, per particle: nearest passing element, lower column on a tie */
    for (Py_ssize_t p = 0; p < P; p++) {
        double g = wide ? wide[p] : gate_m;
        for (Py_ssize_t i = 0; i < N; i++) {
            double px = s->wx[p * N + i], py = s->wy[p * N + i];
            double qx = s->qx[p * N + i], qy = s->qy[p * N + i];
            double best_cost = INFINITY;
            int64_t best = -1;
            /* the point's own line, in the map frame (not at the predicted pose: wide gates) */
            int turned = !wide && !isnan(s->pa[i]);
            double sa = turned ? s->ps[i] * s->hc[p] + s->pc[i] * s->hs[p] : 0.0;
            double ca = turned ? s->pc[i] * s->hc[p] - s->ps[i] * s->hs[p] : 0.0;
            for (Py_ssize_t k = s->cand_start[i]; k < s->cand_start[i + 1]; k++) {
                Py_ssize_t c = s->cand[k], pc = p * C + c;
                if (!s->valid[pc]) continue;
                double nx = s->nx[pc], ny = s->ny[pc];
                double perp = fabs(nx * px + ny * py - s->rho[pc]);
                if (!(perp < g)) continue;
                if (turned && !(fabs(sa * nx - ca * ny) <= s->max_sin)) continue;
                double t_pt = ny * px - nx * py;
                const double *e = s->seg + 4 * pc;
                double t0 = ny * e[0] - nx * e[1];
                double t1 = ny * e[2] - nx * e[3];
                double lo = t0 < t1 ? t0 : t1, hi = t0 < t1 ? t1 : t0;
                if (!(t_pt > lo - s->margin && t_pt < hi + s->margin)) continue;
                if (!(s->fx[pc] * qx + s->fy[pc] * qy < 0.0)) continue;
                if (perp < best_cost) {
                    best_cost = perp;
                    best = c;
                }
            }
            idx[p * N + i] = best;
        }
    }
    return 1;
}

static PyObject *gn_points(PyObject *self, PyObject *args) {
    Py_buffer b_x, b_mean, b_info, b_pts, b_nx, b_ny, b_rho, b_seg, b_fx, b_fy, b_valid, b_gate, b_h, b_idx,
        b_pa;
    Py_ssize_t P, N, C;
    int iterations, reassociate_after;
    double gate_m, margin, robust, sigma, max_sin;
    if (!PyArg_ParseTuple(args, "w*y*y*y*y*y*y*y*y*y*y*y*w*w*y*nnniiddddd", &b_x, &b_mean, &b_info, &b_pts,
                          &b_nx, &b_ny, &b_rho, &b_seg, &b_fx, &b_fy, &b_valid, &b_gate, &b_h, &b_idx, &b_pa,
                          &P, &N, &C, &iterations, &reassociate_after, &gate_m, &margin, &robust, &sigma,
                          &max_sin))
        return NULL;
    Py_buffer *all[] = {&b_x, &b_mean, &b_info, &b_pts, &b_nx, &b_ny, &b_rho, &b_seg,
                        &b_fx, &b_fy, &b_valid, &b_gate, &b_h, &b_idx, &b_pa};
    Py_ssize_t need[] = {P * 3 * 8, P * 3 * 8, P * 9 * 8, N * 2 * 8, P * C * 8,
                         P * C * 8, P * C * 8, P * C * 4 * 8, P * C * 8, P * C * 8,
                         P * C,     P * 8,     P * 9 * 8,     P * N * 8, N * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("gn_points", all, need, n_buf)) goto done;
    Assoc s = {P, N, C, b_pts.buf, b_nx.buf, b_ny.buf, b_rho.buf, b_seg.buf, b_fx.buf, b_fy.buf, b_valid.buf,
               margin, b_pa.buf, max_sin};
    size_t pn = (size_t)(P * N > 0 ? P * N : 1);
    double *work = malloc(sizeof(double) * (4 * pn + 4 * (size_t)C + 4 * (size_t)N + 2 * (size_t)P + 1));
    Py_ssize_t *starts = malloc(sizeof(Py_ssize_t) * ((size_t)N + 1));
    int ok = work && starts;
    if (ok) {
        s.qx = work;
        s.qy = work + pn;
        s.wx = work + 2 * pn;
        s.wy = work + 3 * pn;
        s.lo_x = work + 4 * pn;
        s.hi_x = s.lo_x + C;
        s.lo_y = s.hi_x + C;
        s.hi_y = s.lo_y + C;
        s.ref_x = s.hi_y + C;
        s.ref_y = s.ref_x + N;
        s.hc = s.ref_y + N;
        s.hs = s.hc + P;
        s.pc = s.hs + P;
        s.ps = s.pc + N;
        for (Py_ssize_t i = 0; i < N; i++) { /* the points' lines turn with each particle (rotate) */
            s.pc[i] = cos(s.pa[i]);
            s.ps[i] = sin(s.pa[i]);
        }
        s.cand_start = starts;
    }
    double *x = b_x.buf;
    const double *mean = b_mean.buf, *info = b_info.buf;
    double *h = b_h.buf;
    int64_t *idx = b_idx.buf;
    const double inv_s2 = 1.0 / (sigma * sigma);
    Py_BEGIN_ALLOW_THREADS
    memset(h, 0, sizeof(double) * 9 * (size_t)P);
    for (Py_ssize_t k = 0; ok && k < P * N; k++) idx[k] = -1;
    for (int it = 0; ok && it < iterations; it++) {
        rotate(&s, x);
        if ((it == 0 || it == reassociate_after) && !associate(&s, it == 0 ? b_gate.buf : NULL, gate_m, idx)) {
            ok = 0;
            break;
        }
        for (Py_ssize_t p = 0; p < P; p++) {
            /* the symmetric 3x3 information and the gradient, in registers */
            double h00 = 0, h01 = 0, h02 = 0, h11 = 0, h12 = 0, h22 = 0, g0 = 0, g1 = 0, g2 = 0;
            double tx = x[3 * p], ty = x[3 * p + 1];
            const int64_t *assoc = idx + p * N;
            const double *qxp = s.qx + p * N, *qyp = s.qy + p * N;
            const double *nxp = s.nx + p * C, *nyp = s.ny + p * C, *rp = s.rho + p * C;
            for (Py_ssize_t i = 0; i < N; i++) {
                int64_t c = assoc[i];
                if (c < 0) continue;
                double nx = nxp[c], ny = nyp[c];
                double qx = qxp[i], qy = qyp[i];
                double r = nx * (qx + tx) + ny * (qy + ty) - rp[c];
                double jt = ny * qx - nx * qy;
                double u = r / robust;
                double w = inv_s2 / (1.0 + u * u);
                double wx = w * nx, wy = w * ny, wt = w * jt;
                h00 += wx * nx;
                h01 += wx * ny;
                h02 += wx * jt;
                h11 += wy * ny;
                h12 += wy * jt;
                h22 += wt * jt;
                g0 += wx * r;
                g1 += wy * r;
                g2 += wt * r;
            }
            double hh[9] = {h00, h01, h02, h01, h11, h12, h02, h12, h22}, g[3] = {g0, g1, g2};
            memcpy(h + 9 * p, hh, sizeof hh);
            const double *ip = info + 9 * p;
            double d[3] = {x[3 * p] - mean[3 * p], x[3 * p + 1] - mean[3 * p + 1],
                           wrap_angle(x[3 * p + 2] - mean[3 * p + 2])};
            double a[9], rhs[3], step[3];
            for (int r = 0; r < 3; r++) {
                rhs[r] = -(g[r] + (ip[3 * r] * d[0] + ip[3 * r + 1] * d[1] + ip[3 * r + 2] * d[2]));
                for (int c = 0; c < 3; c++) a[3 * r + c] = hh[3 * r + c] + ip[3 * r + c];
            }
            if (!solve3(a, rhs, step)) step[0] = step[1] = step[2] = 0.0;
            x[3 * p] += step[0];
            x[3 * p + 1] += step[1];
            x[3 * p + 2] = wrap_angle(x[3 * p + 2] + step[2]);
        }
    }
    Py_END_ALLOW_THREADS
    if (ok) {
        result = Py_None;
        Py_INCREF(result);
    } else {
        PyErr_NoMemory();
    }
    free(s.cand);
    free(work);
    free(starts);
done:
    release(all, n_buf);
    return result;
}

/* association.associate: for every (particle, observation) the element of least cost among those
 * inside every gate (the first on a tie, as numpy's argmin), or -1. */
static PyObject *associate_segments(PyObject *self, PyObject *args) {
    Py_buffer b_of, b_cx, b_cy, b_oe, b_va, b_vp, b_mc, b_ms, b_mr, b_mf, b_seg, b_valid, b_idx, b_cost, b_da,
        b_dp;
    Py_ssize_t P, O, C;
    double angle_gate, perp_gate, gap_gate, sigma_gap;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*y*y*y*y*w*w*w*w*nnndddd", &b_of, &b_cx, &b_cy, &b_oe, &b_va,
                          &b_vp, &b_mc, &b_ms, &b_mr, &b_mf, &b_seg, &b_valid, &b_idx, &b_cost, &b_da, &b_dp,
                          &P, &O, &C, &angle_gate, &perp_gate, &gap_gate, &sigma_gap))
        return NULL;
    Py_buffer *all[] = {&b_of, &b_cx, &b_cy, &b_oe, &b_va, &b_vp, &b_mc, &b_ms,
                        &b_mr, &b_mf, &b_seg, &b_valid, &b_idx, &b_cost, &b_da, &b_dp};
    Py_ssize_t po = P * O * 8, pc = P * C * 8;
    Py_ssize_t need[] = {po, po, po, 4 * po, po, po, pc, pc, pc, pc, 4 * pc, P * C, po, po, po, po};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("associate_segments", all, need, n_buf)) goto done;
    const double *of = b_of.buf, *cx = b_cx.buf, *cy = b_cy.buf, *oe = b_oe.buf, *va = b_va.buf, *vp = b_vp.buf;
    const double *mc = b_mc.buf, *ms = b_ms.buf, *mr = b_mr.buf, *mf = b_mf.buf, *seg = b_seg.buf;
    const uint8_t *valid = b_valid.buf;
    int64_t *idx = b_idx.buf;
    double *cost_out = b_cost.buf, *da_out = b_da.buf, *dp_out = b_dp.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < P; p++) {
        for (Py_ssize_t o = 0; o < O; o++) {
            Py_ssize_t k = p * O + o;
            const double *e = oe + 4 * k;
            double best = INFINITY, best_da = 0.0, best_dp = 0.0;
            int64_t best_c = -1;
            for (Py_ssize_t c = 0; c < C; c++) {
                Py_ssize_t j = p * C + c;
                if (!valid[j]) continue;
                double d_angle = fabs(wrap_angle(of[k] - mf[j]));
                if (!(d_angle < angle_gate)) continue;
                double cs = mc[j], sn = ms[j];
                double d_perp = cs * cx[k] + sn * cy[k] - mr[j];
                if (!(fabs(d_perp) < perp_gate)) continue;
                const double *m = seg + 4 * j;
                double gap = -interval_overlap(-sn * e[0] + cs * e[1], -sn * e[2] + cs * e[3],
                                               -sn * m[0] + cs * m[1], -sn * m[2] + cs * m[3]);
                if (gap < 0.0) gap = 0.0;
                if (!(gap < gap_gate)) continue;
                double g = gap / sigma_gap;
                double cost = d_angle * d_angle / va[k] + d_perp * d_perp / vp[k] + g * g;
                if (cost < best) {
                    best = cost;
                    best_c = c;
                    best_da = d_angle;
                    best_dp = d_perp;
                }
            }
            idx[k] = best_c;
            cost_out[k] = best;
            da_out[k] = best_c >= 0 ? best_da : INFINITY;
            dp_out[k] = best_c >= 0 ? best_dp : INFINITY;
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

/* update.visibility: for every (particle, element) how many of its sample points the beams passed
 * through, and whether it was wholly in view (see update.py). */
static PyObject *visibility(PyObject *self, PyObject *args) {
    Py_buffer b_seg, b_nc, b_ns, b_fc, b_fs, b_valid, b_lp, b_ranges, b_samples, b_through, b_view;
    Py_ssize_t P, C, B;
    double a0, da, usable, sin_min_inc, margin_m, margin_rel, min_span;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*y*w*w*nnnddddddd", &b_seg, &b_nc, &b_ns, &b_fc, &b_fs,
                          &b_valid, &b_lp, &b_ranges, &b_samples, &b_through, &b_view, &P, &C, &B, &a0, &da,
                          &usable, &sin_min_inc, &margin_m, &margin_rel, &min_span))
        return NULL;
    Py_buffer *all[] = {&b_seg, &b_nc, &b_ns, &b_fc, &b_fs, &b_valid, &b_lp, &b_ranges, &b_samples, &b_through, &b_view};
    Py_ssize_t pc = P * C * 8;
    Py_ssize_t need[] = {4 * pc, pc, pc, pc, pc, P * C, P * 3 * 8, B * 8, 3 * 8, pc, P * C};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("visibility", all, need, n_buf)) goto done;
    const double *seg = b_seg.buf, *nc = b_nc.buf, *ns = b_ns.buf, *fc = b_fc.buf, *fs = b_fs.buf;
    const double *lp = b_lp.buf, *ranges = b_ranges.buf, *ts = b_samples.buf;
    const uint8_t *valid = b_valid.buf;
    int64_t *through = b_through.buf;
    uint8_t *view = b_view.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < P; p++) {
        double lx = lp[3 * p], ly = lp[3 * p + 1], lth = lp[3 * p + 2];
        for (Py_ssize_t c = 0; c < C; c++) {
            Py_ssize_t j = p * C + c;
            through[j] = 0;
            view[j] = 0;
            if (!valid[j]) continue;
            const double *e = seg + 4 * j;
            int64_t n_through = 0;
            int all_end = 1;
            double bearing[3];
            for (int k = 0; k < 3; k++) {
                double t = ts[k], u = 1 - t;
                double rx = (e[0] * u + e[2] * t) - lx, ry = (e[1] * u + e[3] * t) - ly;
                double dist = sqrt(rx * rx + ry * ry);
                double cos_inc = fabs(nc[j] * rx + ns[j] * ry) / (dist > 1e-9 ? dist : 1e-9);
                int steep = cos_inc > sin_min_inc;
                bearing[k] = 0.0;
                if (!(steep && dist < usable && dist > 0.1)) { /* neither seen through nor in view */
                    all_end = 0;
                    continue;
                }
                double b = wrap_angle(atan2(ry, rx) - lth);
                bearing[k] = b;
                double f = rint((b - a0) / da);
                int inside = f >= 0 && f < (double)B;
                Py_ssize_t beam = !(f >= 0) ? 0 : (f > (double)(B - 1) ? B - 1 : (Py_ssize_t)f);
                double measured = ranges[beam];
                int has_return = isfinite(measured) && measured < usable;
                double margin = margin_m + margin_rel * dist;
                if (inside && steep && (measured > dist + margin || !has_return)) n_through++;
                int front = fc[j] * rx + fs[j] * ry < 0;
                if (!(inside && front && steep && has_return && fabs(measured - dist) <= margin)) all_end = 0;
            }
            double span = fabs(wrap_angle(bearing[2] - bearing[0])) / (ts[2] - ts[0]);
            through[j] = n_through;
            view[j] = (uint8_t)(all_end && span >= min_span);
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

typedef struct {
    int64_t cx, cy;
    Py_ssize_t i;
} Cell;

static int cell_order(const void *a, const void *b) {
    const Cell *u = a, *v = b;
    if (u->cx != v->cx) return u->cx < v->cx ? -1 : 1;
    if (u->cy != v->cy) return u->cy < v->cy ? -1 : 1;
    return u->i < v->i ? -1 : (u->i > v->i);
}

/* first index in cells[lo, hi) not ordered before (cx, cy) */
static Py_ssize_t lower_bound(const Cell *cells, Py_ssize_t lo, Py_ssize_t hi, int64_t cx, int64_t cy) {
    while (lo < hi) {
        Py_ssize_t mid = lo + (hi - lo) / 2;
        if (cells[mid].cx < cx || (cells[mid].cx == cx && cells[mid].cy < cy))
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo;
}

/* The smaller of best2 and the squared distances from (x, y) to samples order[from..to). */
static double nearest2(const double *sp, const Py_ssize_t *order, Py_ssize_t from, Py_ssize_t to, double x,
                       double y, double best2) {
    for (Py_ssize_t k = from; k < to; k++) {
        double dx = sp[2 * order[k]] - x, dy = sp[2 * order[k] + 1] - y;
        double dd = dx * dx + dy * dy;
        if (dd < best2) best2 = dd;
    }
    return best2;
}

/* Distance from each query point to the nearest sample point, if nearer than radius, else inf
 * (a k-d tree's query with distance_upper_bound): the samples sorted by grid cell of the radius'
 * size, each query looking in the 3 x 3 cells around its own. */
static PyObject *nearest_within(PyObject *self, PyObject *args) {
    Py_buffer b_s, b_q, b_d;
    Py_ssize_t S, Q;
    double radius;
    if (!PyArg_ParseTuple(args, "y*y*w*nnd", &b_s, &b_q, &b_d, &S, &Q, &radius)) return NULL;
    Py_buffer *all[] = {&b_s, &b_q, &b_d};
    Py_ssize_t need[] = {S * 2 * 8, Q * 2 * 8, Q * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("nearest_within", all, need, n_buf)) goto done;
    if (!(radius > 0.0) || !isfinite(radius)) {
        PyErr_Format(PyExc_ValueError, "nearest_within: radius must be finite and > 0, got %g", radius);
        goto done;
    }
    const double *sp = b_s.buf, *qp = b_q.buf;
    double *d = b_d.buf;
    Cell *cells = malloc(sizeof(Cell) * (size_t)(S > 0 ? S : 1));
    if (!cells) {
        PyErr_NoMemory();
        goto done;
    }
    int no_memory = 0;
    Py_BEGIN_ALLOW_THREADS
    Py_ssize_t n = 0;
    int64_t x0 = INT64_MAX, y0 = INT64_MAX, x1 = INT64_MIN, y1 = INT64_MIN;
    for (Py_ssize_t i = 0; i < S; i++) {
        double fx = floor(sp[2 * i] / radius), fy = floor(sp[2 * i + 1] / radius);
        if (!(fabs(fx) < 4e18 && fabs(fy) < 4e18)) continue; /* not finite: never nearest */
        cells[n].cx = (int64_t)fx;
        cells[n].cy = (int64_t)fy;
        cells[n].i = i;
        if (cells[n].cx < x0) x0 = cells[n].cx;
        if (cells[n].cx > x1) x1 = cells[n].cx;
        if (cells[n].cy < y0) y0 = cells[n].cy;
        if (cells[n].cy > y1) y1 = cells[n].cy;
        n++;
    }
    /* the samples in cell order (``order``): over a dense grid of cells when the samples' extent is
     * small (a local map), counted into it; else sorted by cell (samples spread far apart) */
    double area = n ? ((double)(x1 - x0) + 1.0) * ((double)(y1 - y0) + 1.0) : 0.0;
    int dense = n && area <= 8.0 * (double)n + 4096.0;
    Py_ssize_t W = dense ? (Py_ssize_t)(x1 - x0 + 1) : 0, H = dense ? (Py_ssize_t)(y1 - y0 + 1) : 0;
    Py_ssize_t *start = dense ? calloc((size_t)(W * H + 1), sizeof(Py_ssize_t)) : NULL;
    Py_ssize_t *order = malloc(sizeof(Py_ssize_t) * (size_t)(n > 0 ? n : 1));
    if (dense && start && order) {
        for (Py_ssize_t k = 0; k < n; k++) start[(cells[k].cx - x0) * H + (cells[k].cy - y0) + 1]++;
        for (Py_ssize_t c = 0; c < W * H; c++) start[c + 1] += start[c];
        for (Py_ssize_t k = 0; k < n; k++) order[start[(cells[k].cx - x0) * H + (cells[k].cy - y0)]++] = cells[k].i;
        for (Py_ssize_t c = W * H; c > 0; c--) start[c] = start[c - 1]; /* back to the first of each */
        start[0] = 0;
    } else if (order) {
        dense = 0;
        qsort(cells, (size_t)n, sizeof(Cell), cell_order);
        for (Py_ssize_t k = 0; k < n; k++) order[k] = cells[k].i;
    }
    for (Py_ssize_t q = 0; order && q < Q; q++) {
        double x = qp[2 * q], y = qp[2 * q + 1];
        double best2 = INFINITY;
        double fx = floor(x / radius), fy = floor(y / radius);
        if (fabs(fx) < 4e18 && fabs(fy) < 4e18) {
            int64_t cx = (int64_t)fx, cy = (int64_t)fy;
            for (int64_t gx = cx - 1; gx <= cx + 1; gx++) {
                if (dense) {
                    for (int64_t gy = cy - 1; gy <= cy + 1; gy++) {
                        if (gx < x0 || gx > x1 || gy < y0 || gy > y1) continue;
                        Py_ssize_t c = (Py_ssize_t)((gx - x0) * H + (gy - y0));
                        best2 = nearest2(sp, order, start[c], start[c + 1], x, y, best2);
                    }
                } else {
                    Py_ssize_t from = lower_bound(cells, 0, n, gx, cy - 1), to = from;
                    while (to < n && cells[to].cx == gx && cells[to].cy <= cy + 1) to++;
                    best2 = nearest2(sp, order, from, to, x, y, best2);
                }
            }
        }
        double best = sqrt(best2);
        d[q] = best < radius ? best : INFINITY;
    }
    no_memory = !order;
    free(start);
    free(order);
    Py_END_ALLOW_THREADS
    free(cells);
    if (no_memory) {
        PyErr_NoMemory();
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

/* ---- extraction (extraction.py): the split and merge rounds ---------------------------------- */

/* extraction._split: iterative end-point fit. Splitting every piece once per round, as the numpy
 * code does, ends where splitting each piece to the end does: pieces never interact. */
static PyObject *split_pieces(PyObject *self, PyObject *args) {
    Py_buffer b_pts, b_thr, b_starts, b_out;
    Py_ssize_t K, S;
    long min_points;
    if (!PyArg_ParseTuple(args, "y*y*y*w*nnl", &b_pts, &b_thr, &b_starts, &b_out, &K, &S, &min_points))
        return NULL;
    Py_buffer *all[] = {&b_pts, &b_thr, &b_starts, &b_out};
    Py_ssize_t need[] = {K * 2 * 8, K * 8, S * 8, K * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("split_pieces", all, need, n_buf)) goto done;
    const double *pts = b_pts.buf, *thr = b_thr.buf;
    const int64_t *starts = b_starts.buf;
    int64_t *out = b_out.buf; /* at most K starts */
    if (!starts_ok("split_pieces", starts, S, K)) goto done;
    int64_t *stack = malloc(sizeof(int64_t) * 2 * (size_t)(K + 1));
    if (!stack) {
        PyErr_NoMemory();
        goto done;
    }
    Py_ssize_t n_out = 0;
    Py_BEGIN_ALLOW_THREADS
    /* depth first, right half pushed first: the starts come out in order */
    for (Py_ssize_t j = 0; j < S; j++) {
        Py_ssize_t top = 0;
        stack[top++] = starts[j];
        stack[top++] = j + 1 < S ? starts[j + 1] : K;
        while (top) {
            int64_t e = stack[--top], a = stack[--top];
            int64_t split = -1;
            if (e - a >= min_points) {
                double ax = pts[2 * a], ay = pts[2 * a + 1];
                double cx = pts[2 * (e - 1)] - ax, cy = pts[2 * (e - 1) + 1] - ay;
                double length = hypot(cx, cy);
                double far = -INFINITY;
                int beyond = 0;
                for (int64_t i = a; i < e; i++) {
                    double rx = pts[2 * i] - ax, ry = pts[2 * i + 1] - ay;
                    double d = length > 0 ? fabs(cx * ry - cy * rx) / length : hypot(rx, ry);
                    if (d > thr[i]) beyond = 1;
                    if (d > far) {
                        far = d;
                        split = i;
                    }
                }
                if (!beyond) split = -1;
            }
            if (split > a) {
                stack[top++] = split;
                stack[top++] = e;
                stack[top++] = a;
                stack[top++] = split;
            } else {
                out[n_out++] = a;
            }
        }
    }
    Py_END_ALLOW_THREADS
    free(stack);
    result = PyLong_FromSsize_t(n_out);
done:
    release(all, n_buf);
    return result;
}

/* lines.fit_lines for one set of moments */
static void fit_line(const double *m, double *alpha_out, double *rho_out, double *sigma2_out) {
    double n = m[0];
    double xc = m[1] / n, yc = m[2] / n;
    double sxx = m[3] - n * xc * xc, sxy = m[4] - n * xc * yc, syy = m[5] - n * yc * yc;
    double alpha = 0.5 * atan2(-2.0 * sxy, syy - sxx);
    double rho = xc * cos(alpha) + yc * sin(alpha);
    if (rho < 0.0) alpha = alpha + M_PI;
    alpha = wrap_angle(alpha);
    rho = fabs(rho);
    double lam = 0.5 * (sxx + syy) - hypot(0.5 * (sxx - syy), sxy);
    double sigma2 = (lam < 0.0 ? 0.0 : lam) / n;
    if (!(n >= 2)) alpha = rho = sigma2 = NAN;
    *alpha_out = alpha;
    *rho_out = rho;
    *sigma2_out = sigma2;
}

/* var(alpha) of lines.line_covariance, with the point variance floored as extraction does */
static double alpha_variance(const double *m, double alpha, double sigma2, double floor2) {
    double n = m[0];
    double xc = m[1] / n, yc = m[2] / n;
    double sxx = m[3] - n * xc * xc, sxy = m[4] - n * xc * yc, syy = m[5] - n * yc * yc;
    double c = cos(alpha), s = sin(alpha);
    double s_perp = s * s * sxx - 2.0 * c * s * sxy + c * c * syy;
    double v = sigma2 > floor2 || isnan(sigma2) ? sigma2 : floor2;
    return v / s_perp;
}

/* extraction._merge: adjacent collinear pieces of one cluster merged, in rounds. */
static PyObject *merge_pieces(PyObject *self, PyObject *args) {
    Py_buffer b_pts, b_thr, b_starts, b_cluster;
    Py_ssize_t K, S;
    double max_rms, range_sigma, merge_angle, n_sigma;
    if (!PyArg_ParseTuple(args, "y*y*w*w*nndddd", &b_pts, &b_thr, &b_starts, &b_cluster, &K, &S, &max_rms,
                          &range_sigma, &merge_angle, &n_sigma))
        return NULL;
    Py_buffer *all[] = {&b_pts, &b_thr, &b_starts, &b_cluster};
    Py_ssize_t need[] = {K * 2 * 8, K * 8, S * 8, S * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("merge_pieces", all, need, n_buf)) goto done;
    const double *pts = b_pts.buf, *thr = b_thr.buf;
    int64_t *starts = b_starts.buf, *cluster = b_cluster.buf;
    if (!starts_ok("merge_pieces", starts, S, K)) goto done;
    size_t s1 = (size_t)(S > 0 ? S : 1);
    double *mom = malloc(sizeof(double) * 6 * s1);
    double *alpha = malloc(sizeof(double) * 4 * s1), *var_a = alpha + s1, *cost = alpha + 2 * s1;
    double *mm = malloc(sizeof(double) * 6 * s1), *m_alpha = malloc(sizeof(double) * 3 * s1);
    double *m_rho = m_alpha + s1, *m_sigma2 = m_alpha + 2 * s1;
    uint8_t *ok = malloc(s1), *keep = malloc(s1);
    if (!mom || !alpha || !mm || !m_alpha || !ok || !keep) {
        free(mom), free(alpha), free(mm), free(m_alpha), free(ok), free(keep);
        PyErr_NoMemory();
        goto done;
    }
    Py_ssize_t n = S;
    Py_BEGIN_ALLOW_THREADS
    /* the pieces' moments, summed in point order (as numpy's bincount) */
    for (Py_ssize_t j = 0; j < n; j++) {
        double *m = mom + 6 * j;
        m[0] = m[1] = m[2] = m[3] = m[4] = m[5] = 0.0;
        int64_t e = j + 1 < n ? starts[j + 1] : K;
        for (int64_t i = starts[j]; i < e; i++) {
            double x = pts[2 * i], y = pts[2 * i + 1];
            m[0] += 1.0;
            m[1] += x;
            m[2] += y;
            m[3] += x * x;
            m[4] += x * y;
            m[5] += y * y;
        }
    }
    while (n > 1) {
        int any_ok = 0;
        for (Py_ssize_t j = 0; j + 1 < n; j++) {
            for (int f = 0; f < 6; f++) mm[6 * j + f] = mom[6 * j + f] + mom[6 * (j + 1) + f];
            fit_line(mm + 6 * j, m_alpha + j, m_rho + j, m_sigma2 + j);
            ok[j] = cluster[j] == cluster[j + 1] && m_sigma2[j] <= max_rms * max_rms;
            any_ok |= ok[j];
        }
        if (!any_ok) break;
        for (Py_ssize_t j = 0; j < n; j++) {
            double r, s2;
            fit_line(mom + 6 * j, alpha + j, &r, &s2);
            var_a[j] = alpha_variance(mom + 6 * j, alpha[j], s2, range_sigma * range_sigma);
        }
        any_ok = 0;
        for (Py_ssize_t j = 0; j + 1 < n; j++) {
            if (!ok[j]) continue;
            /* every point of the pair within its split threshold of the merged line */
            double c = cos(m_alpha[j]), s = sin(m_alpha[j]);
            int64_t e = j + 2 < n ? starts[j + 2] : K;
            double worst = 0.0;
            for (int64_t i = starts[j]; i < e; i++) {
                double r = fabs(c * pts[2 * i] + s * pts[2 * i + 1] - m_rho[j]) / thr[i];
                if (r > worst || isnan(r)) worst = r;
            }
            double gate = merge_angle + n_sigma * sqrt(var_a[j] + var_a[j + 1]);
            double d = fabs(wrap_angle(alpha[j] - alpha[j + 1]));
            d = d < M_PI - d ? d : M_PI - d;
            ok[j] = !(d > gate) && worst <= 1.0;
            any_ok |= ok[j];
        }
        if (!any_ok) break;
        for (Py_ssize_t j = 0; j + 1 < n; j++) cost[j] = ok[j] ? m_sigma2[j] : INFINITY;
        for (Py_ssize_t j = 0; j < n; j++) keep[j] = 1;
        for (Py_ssize_t j = 0; j + 1 < n; j++) {
            double before = j > 0 ? cost[j - 1] : INFINITY, after = j + 2 < n ? cost[j + 1] : INFINITY;
            if (ok[j] && cost[j] < before && cost[j] <= after) {
                for (int f = 0; f < 6; f++) mom[6 * j + f] += mom[6 * (j + 1) + f];
                keep[j + 1] = 0;
            }
        }
        Py_ssize_t w = 0;
        for (Py_ssize_t j = 0; j < n; j++) {
            if (!keep[j]) continue;
            starts[w] = starts[j];
            cluster[w] = cluster[j];
            memmove(mom + 6 * w, mom + 6 * j, 6 * sizeof(double));
            w++;
        }
        n = w;
    }
    Py_END_ALLOW_THREADS
    free(mom), free(alpha), free(mm), free(m_alpha), free(ok), free(keep);
    result = PyLong_FromSsize_t(n);
done:
    release(all, n_buf);
    return result;
}

/* FastSLAM._local_columns: the columns with an element, in any of the particles ``rows``, whose
 * distance from (cx, cy) to its midpoint less its half length is below ``limit``. */
static PyObject *local_columns(PyObject *self, PyObject *args) {
    Py_buffer b_valid, b_seg, b_rows, b_out;
    Py_ssize_t P, M, R;
    double cx, cy, limit;
    if (!PyArg_ParseTuple(args, "y*y*y*w*nnnddd", &b_valid, &b_seg, &b_rows, &b_out, &P, &M, &R, &cx, &cy, &limit))
        return NULL;
    Py_buffer *all[] = {&b_valid, &b_seg, &b_rows, &b_out};
    Py_ssize_t need[] = {P * M, P * M * 4 * 8, R * 8, M * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("local_columns", all, need, n_buf)) goto done;
    const uint8_t *valid = b_valid.buf;
    const double *seg = b_seg.buf;
    const int64_t *rows = b_rows.buf;
    int64_t *out = b_out.buf;
    for (Py_ssize_t r = 0; r < R; r++) {
        if (rows[r] < 0 || rows[r] >= P) {
            PyErr_Format(PyExc_IndexError, "local_columns: row %lld is not a particle", (long long)rows[r]);
            goto done;
        }
    }
    Py_ssize_t n = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t c = 0; c < M; c++) {
        for (Py_ssize_t r = 0; r < R; r++) {
            Py_ssize_t j = rows[r] * M + c;
            if (!valid[j]) continue;
            const double *e = seg + 4 * j;
            double mx = 0.5 * (e[0] + e[2]) - cx, my = 0.5 * (e[1] + e[3]) - cy;
            double lx = e[2] - e[0], ly = e[3] - e[1];
            if (sqrt(mx * mx + my * my) - 0.5 * sqrt(lx * lx + ly * ly) < limit) {
                out[n++] = c;
                break;
            }
        }
    }
    Py_END_ALLOW_THREADS
    result = PyLong_FromSsize_t(n);
done:
    release(all, n_buf);
    return result;
}

/* update._redundant_pairs: out[p, x, j] — column x and recent column r = recent[j] both valid,
 * distinct, facing the same way, r's midpoint on x's line and their extents along it overlapping. */
static PyObject *redundant_pairs(PyObject *self, PyObject *args) {
    Py_buffer b_valid, b_seg, b_c, b_s, b_rho, b_facing, b_recent, b_out;
    Py_ssize_t P, C, R;
    double max_angle, max_perp, min_overlap;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*w*nnnddd", &b_valid, &b_seg, &b_c, &b_s, &b_rho, &b_facing,
                          &b_recent, &b_out, &P, &C, &R, &max_angle, &max_perp, &min_overlap))
        return NULL;
    Py_buffer *all[] = {&b_valid, &b_seg, &b_c, &b_s, &b_rho, &b_facing, &b_recent, &b_out};
    Py_ssize_t pc = P * C * 8;
    Py_ssize_t need[] = {P * C, 4 * pc, pc, pc, pc, pc, R * 8, P * C * R};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("redundant_pairs", all, need, n_buf)) goto done;
    const uint8_t *valid = b_valid.buf;
    const double *seg = b_seg.buf, *ca = b_c.buf, *sa = b_s.buf, *rho = b_rho.buf, *facing = b_facing.buf;
    const int64_t *recent = b_recent.buf;
    uint8_t *out = b_out.buf;
    for (Py_ssize_t j = 0; j < R; j++) {
        if (recent[j] < 0 || recent[j] >= C) {
            PyErr_Format(PyExc_IndexError, "redundant_pairs: recent column %lld of %zd", (long long)recent[j], C);
            goto done;
        }
    }
    Py_BEGIN_ALLOW_THREADS
    memset(out, 0, (size_t)(P * C * R));
    for (Py_ssize_t p = 0; p < P; p++) {
        for (Py_ssize_t j = 0; j < R; j++) {
            Py_ssize_t r = recent[j], pr = p * C + r;
            if (!valid[pr]) continue;
            const double *er = seg + 4 * pr;
            double mx = 0.5 * (er[0] + er[2]), my = 0.5 * (er[1] + er[3]);
            for (Py_ssize_t x = 0; x < C; x++) {
                Py_ssize_t px = p * C + x;
                if (x == r || !valid[px]) continue;
                if (!(fabs(wrap_angle(facing[px] - facing[pr])) < max_angle)) continue;
                double c = ca[px], s = sa[px];
                if (!(fabs(c * mx + s * my - rho[px]) < max_perp)) continue;
                const double *ex = seg + 4 * px;
                double overlap = interval_overlap(-s * ex[0] + c * ex[1], -s * ex[2] + c * ex[3],
                                                  -s * er[0] + c * er[1], -s * er[2] + c * er[3]);
                if (!(overlap > min_overlap)) continue;
                out[(p * C + x) * R + j] = 1;
            }
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

/* association.observe: a scan's segments (robot frame: moments (O,6), ends (O,2,2), facing (O,))
 * moved into every particle's map frame (lines.transform_moments, lines.fit_lines,
 * geometry.apply_segments, the facing turned). */
static PyObject *observe_segments(PyObject *self, PyObject *args) {
    Py_buffer b_poses, b_m, b_e, b_f, b_mo, b_al, b_rh, b_fo, b_eo;
    Py_ssize_t P, O;
    if (!PyArg_ParseTuple(args, "y*y*y*y*w*w*w*w*w*nn", &b_poses, &b_m, &b_e, &b_f, &b_mo, &b_al, &b_rh, &b_fo,
                          &b_eo, &P, &O))
        return NULL;
    Py_buffer *all[] = {&b_poses, &b_m, &b_e, &b_f, &b_mo, &b_al, &b_rh, &b_fo, &b_eo};
    Py_ssize_t po = P * O * 8;
    Py_ssize_t need[] = {P * 3 * 8, O * 6 * 8, O * 4 * 8, O * 8, 6 * po, po, po, po, 4 * po};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("observe_segments", all, need, n_buf)) goto done;
    const double *poses = b_poses.buf, *mr = b_m.buf, *er = b_e.buf, *fr = b_f.buf;
    double *mo = b_mo.buf, *al = b_al.buf, *rh = b_rh.buf, *fo = b_fo.buf, *eo = b_eo.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < P; p++) {
        double tx = poses[3 * p], ty = poses[3 * p + 1], th = poses[3 * p + 2];
        double c = cos(th), s = sin(th);
        for (Py_ssize_t o = 0; o < O; o++) {
            const double *m = mr + 6 * o;
            double n = m[0], sx = m[1], sy = m[2], sxx = m[3], sxy = m[4], syy = m[5];
            double ux = c * sx - s * sy, uy = s * sx + c * sy;
            double rxx = c * c * sxx - 2.0 * c * s * sxy + s * s * syy;
            double ryy = s * s * sxx + 2.0 * c * s * sxy + c * c * syy;
            double rxy = c * s * (sxx - syy) + (c * c - s * s) * sxy;
            double *q = mo + 6 * (p * O + o);
            q[0] = n;
            q[1] = ux + n * tx;
            q[2] = uy + n * ty;
            q[3] = rxx + 2.0 * ux * tx + n * tx * tx;
            q[4] = rxy + ux * ty + uy * tx + n * tx * ty;
            q[5] = ryy + 2.0 * uy * ty + n * ty * ty;
            double sig2;
            fit_line(q, al + p * O + o, rh + p * O + o, &sig2);
            const double *e = er + 4 * o;
            double *f = eo + 4 * (p * O + o);
            for (int k = 0; k < 2; k++) {
                f[2 * k] = c * e[2 * k] - s * e[2 * k + 1] + tx;
                f[2 * k + 1] = s * e[2 * k] + c * e[2 * k + 1] + ty;
            }
            fo[p * O + o] = wrap_angle(fr[o] + th);
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

/* geometry.sample_segments' points: segment i of (S,2,2) cut into counts[i] equal pieces, a point
 * at the middle of each, into out (K = sum of counts). */
static PyObject *segment_samples(PyObject *self, PyObject *args) {
    Py_buffer b_seg, b_counts, b_out;
    Py_ssize_t S, K;
    if (!PyArg_ParseTuple(args, "y*y*w*nn", &b_seg, &b_counts, &b_out, &S, &K)) return NULL;
    Py_buffer *all[] = {&b_seg, &b_counts, &b_out};
    Py_ssize_t need[] = {S * 4 * 8, S * 8, K * 2 * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("segment_samples", all, need, n_buf)) goto done;
    const double *seg = b_seg.buf;
    const int64_t *counts = b_counts.buf;
    double *out = b_out.buf;
    Py_ssize_t total = 0;
    for (Py_ssize_t i = 0; i < S; i++) {
        if (counts[i] < 1) {
            PyErr_Format(PyExc_ValueError, "segment_samples: segment %zd cut into %lld pieces", i,
                         (long long)counts[i]);
            goto done;
        }
        total += counts[i];
    }
    if (total != K) {
        PyErr_Format(PyExc_ValueError, "segment_samples: %zd pieces in all, room for %zd", total, K);
        goto done;
    }
    Py_ssize_t n = 0;
    for (Py_ssize_t i = 0; i < S; i++) {
        const double *e = seg + 4 * i;
        double dx = e[2] - e[0], dy = e[3] - e[1], count = (double)counts[i];
        for (int64_t k = 0; k < counts[i]; k++, n++) {
            double t = ((double)k + 0.5) / count;
            out[2 * n] = e[0] + t * dx;
            out[2 * n + 1] = e[1] + t * dy;
        }
    }
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

static PyMethodDef methods[] = {
    {"gn_points", gn_points, METH_VARARGS,
     "gn_points(x, prior_mean, info_prior, pts, nx, ny, rho, seg, fx, fy, valid, gate_wide, h_out, idx_out, "
     "P, N, C, iterations, reassociate_after, gate_m, margin_m, robust_scale_m, point_sigma_m): "
     "proposal.align_points' Gauss-Newton, in place on x (P,3), h_out (P,3,3), idx_out (P,N) int64."},
    {"associate_segments", associate_segments, METH_VARARGS,
     "associate_segments(obs_facing, cx, cy, obs_ends, var_a, var_p, cos_alpha, sin_alpha, rho, facing, seg, "
     "valid, idx_out, cost_out, d_angle_out, d_perp_out, P, O, C, angle_gate, perp_gate, gap_gate, sigma_gap): "
     "association.associate for all particles x observations x elements."},
    {"visibility", visibility, METH_VARARGS,
     "visibility(seg, cos_alpha, sin_alpha, cos_facing, sin_facing, valid, laser_poses, ranges, samples, "
     "through_out, in_view_out, P, C, B, a0, da, usable, sin_min_incidence, margin_m, margin_rel, min_span): "
     "update.visibility for all particles x elements."},
    {"nearest_within", nearest_within, METH_VARARGS,
     "nearest_within(samples, queries, d_out, S, Q, radius): distance to the nearest sample if < radius, "
     "else inf."},
    {"split_pieces", split_pieces, METH_VARARGS,
     "split_pieces(pts, threshold, starts, out, K, S, min_points) -> count: extraction._split's starts in out."},
    {"merge_pieces", merge_pieces, METH_VARARGS,
     "merge_pieces(pts, threshold, starts, cluster, K, S, max_rms, range_sigma, merge_angle, n_sigma) -> count: "
     "extraction._merge in place on starts and cluster (int64)."},
    {"local_columns", local_columns, METH_VARARGS,
     "local_columns(valid, seg, rows, out, P, M, R, cx, cy, limit) -> count: FastSLAM._local_columns."},
    {"redundant_pairs", redundant_pairs, METH_VARARGS,
     "redundant_pairs(valid, seg, cos_alpha, sin_alpha, rho, facing, recent, out, P, C, R, max_angle, max_perp, "
     "min_overlap): update._redundant_pairs."},
    {"observe_segments", observe_segments, METH_VARARGS,
     "observe_segments(poses, moments, ends, facing, moments_out, alpha_out, rho_out, facing_out, ends_out, P, O): "
     "association.observe."},
    {"segment_samples", segment_samples, METH_VARARGS,
     "segment_samples(seg, counts, out, S, K): geometry.sample_segments' points."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "Compiled kernels of the SLAM's hot loops (see kernels.py).", -1, methods};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
