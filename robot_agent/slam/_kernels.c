/* Compiled kernels of the SLAM's hot loops, with the same arithmetic as their numpy versions.
 *
 * gn_points: the point-to-line Gauss-Newton of proposal.align_points for every particle —
 * association of each scan point with the nearest element (proposal.associate_points) and the
 * normal equations (proposal._point_normal_equations), solved with the motion prior. The numpy
 * version stays the reference (robot_agent/slam/proposal.py) and the fallback when this module
 * is not built; tests/slam/test_kernels.py holds both to the same results.
 *
 * Arrays come through the buffer protocol (no numpy headers at build time): C-contiguous
 * float64 unless said otherwise; the Python wrapper (robot_agent/slam/kernels.py) checks shapes
 * and dtypes and converts. Built with -ffp-contract=off so that a product and a sum are not fused
 * into one rounding the numpy code does not make.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define TWO_PI 6.283185307179586

/* numpy's (a + pi) % 2pi - pi: floor modulo, the result takes the divisor's sign */
static double wrap_angle(double a) {
    double t = a + M_PI;
    double r = fmod(t, TWO_PI);
    if (r != 0.0) {
        if (r < 0.0) r += TWO_PI;
    } else {
        r = 0.0;
    }
    return r - M_PI;
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
    /* workspace */
    double *qx, *qy, *wx, *wy;  /* (P,N) */
    double *lo_x, *hi_x, *lo_y, *hi_y; /* (C,) the candidate boxes */
    double *ref_x, *ref_y;             /* (N,) the points' mean view */
    Py_ssize_t *cand_start; /* (N+1,) */
    Py_ssize_t *cand;       /* candidate columns, capacity cand_cap */
    Py_ssize_t cand_cap;
} Assoc;

static void rotate(Assoc *s, const double *x) {
    for (Py_ssize_t p = 0; p < s->P; p++) {
        double c = cos(x[3 * p + 2]), sn = sin(x[3 * p + 2]);
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

/* Element index (P,N) or -1 of every point at poses x, gates gate (P,): see associate_points. */
static int associate(Assoc *s, const double *x, const double *gate, int64_t *idx) {
    Py_ssize_t P = s->P, N = s->N, C = s->C;
    rotate(s, x);
    for (Py_ssize_t k = 0; k < P * N; k++) idx[k] = -1;
    if (N == 0 || C == 0 || P == 0) return 1;
    /* the candidate pairs: the points' mean view against a box around every particle's copy of
     * each element, widened by the gate, the margin and the particles' spread (a superset) */
    double gmax = gate[0];
    for (Py_ssize_t p = 1; p < P; p++)
        if (gate[p] > gmax) gmax = gate[p];
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
            double d = hypot(s->wx[p * N + i] - ref_x[i], s->wy[p * N + i] - ref_y[i]);
            if (d > spread) spread = d;
        }
    }
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
        double g = gate[p];
        for (Py_ssize_t i = 0; i < N; i++) {
            double px = s->wx[p * N + i], py = s->wy[p * N + i];
            double qx = s->qx[p * N + i], qy = s->qy[p * N + i];
            double best_cost = INFINITY;
            int64_t best = -1;
            for (Py_ssize_t k = s->cand_start[i]; k < s->cand_start[i + 1]; k++) {
                Py_ssize_t c = s->cand[k], pc = p * C + c;
                if (!s->valid[pc]) continue;
                double nx = s->nx[pc], ny = s->ny[pc];
                double perp = fabs(nx * px + ny * py - s->rho[pc]);
                if (!(perp < g)) continue;
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
    Py_buffer b_x, b_mean, b_info, b_pts, b_nx, b_ny, b_rho, b_seg, b_fx, b_fy, b_valid, b_gate, b_h, b_idx;
    Py_ssize_t P, N, C;
    int iterations, reassociate_after;
    double gate_m, margin, robust, sigma;
    if (!PyArg_ParseTuple(args, "w*y*y*y*y*y*y*y*y*y*y*y*w*w*nnniidddd", &b_x, &b_mean, &b_info, &b_pts,
                          &b_nx, &b_ny, &b_rho, &b_seg, &b_fx, &b_fy, &b_valid, &b_gate, &b_h, &b_idx, &P,
                          &N, &C, &iterations, &reassociate_after, &gate_m, &margin, &robust, &sigma))
        return NULL;
    Py_buffer *all[] = {&b_x, &b_mean, &b_info, &b_pts, &b_nx, &b_ny, &b_rho,
                        &b_seg, &b_fx, &b_fy, &b_valid, &b_gate, &b_h, &b_idx};
    Py_ssize_t need[] = {P * 3 * 8, P * 3 * 8, P * 9 * 8, N * 2 * 8, P * C * 8, P * C * 8, P * C * 8,
                         P * C * 4 * 8, P * C * 8, P * C * 8, P * C, P * 8, P * 9 * 8, P * N * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    for (int k = 0; k < n_buf; k++) {
        if (all[k]->len != need[k]) {
            PyErr_Format(PyExc_ValueError, "gn_points: argument %d holds %zd bytes, expected %zd", k,
                         all[k]->len, need[k]);
            goto done;
        }
    }
    Assoc s = {P, N, C, b_pts.buf, b_nx.buf, b_ny.buf, b_rho.buf, b_seg.buf, b_fx.buf, b_fy.buf, b_valid.buf,
               margin};
    size_t pn = (size_t)(P * N > 0 ? P * N : 1);
    double *work = malloc(sizeof(double) * (4 * pn + 4 * (size_t)C + 2 * (size_t)N + 1));
    Py_ssize_t *starts = malloc(sizeof(Py_ssize_t) * ((size_t)N + 1));
    double *gate_normal = malloc(sizeof(double) * (size_t)(P > 0 ? P : 1));
    int ok = work && starts && gate_normal;
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
        s.cand_start = starts;
        s.cand = NULL;
        s.cand_cap = 0;
        for (Py_ssize_t p = 0; p < P; p++) gate_normal[p] = gate_m;
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
        if (it == 0 || it == reassociate_after) {
            if (!associate(&s, x, it == 0 ? (const double *)b_gate.buf : gate_normal, idx)) {
                ok = 0;
                break;
            }
        }
        rotate(&s, x);
        for (Py_ssize_t p = 0; p < P; p++) {
            double hh[9] = {0}, g[3] = {0};
            double tx = x[3 * p], ty = x[3 * p + 1];
            for (Py_ssize_t i = 0; i < N; i++) {
                int64_t c = idx[p * N + i];
                if (c < 0) continue;
                Py_ssize_t pc = p * C + c;
                double nx = s.nx[pc], ny = s.ny[pc];
                double qx = s.qx[p * N + i], qy = s.qy[p * N + i];
                double r = nx * (qx + tx) + ny * (qy + ty) - s.rho[pc];
                double jt = ny * qx - nx * qy;
                double u = r / robust;
                double w = 1.0 / (1.0 + u * u) * inv_s2;
                double j[3] = {nx, ny, jt};
                for (int a = 0; a < 3; a++) {
                    double wa = w * j[a];
                    for (int b = 0; b < 3; b++) hh[3 * a + b] += wa * j[b];
                    g[a] += wa * r;
                }
            }
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
    if (!ok) {
        PyErr_NoMemory();
        free(s.cand);
    } else {
        free(s.cand);
        result = Py_None;
        Py_INCREF(result);
    }
    free(work);
    free(starts);
    free(gate_normal);
done:
    for (int k = 0; k < n_buf; k++) PyBuffer_Release(all[k]);
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
    for (int k = 0; k < n_buf; k++) {
        if (all[k]->len != need[k]) {
            PyErr_Format(PyExc_ValueError, "associate_segments: argument %d holds %zd bytes, expected %zd", k,
                         all[k]->len, need[k]);
            goto done;
        }
    }
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
                double to0 = -sn * e[0] + cs * e[1], to1 = -sn * e[2] + cs * e[3];
                double tm0 = -sn * m[0] + cs * m[1], tm1 = -sn * m[2] + cs * m[3];
                double lo_o = to0 < to1 ? to0 : to1, hi_o = to0 < to1 ? to1 : to0;
                double lo_m = tm0 < tm1 ? tm0 : tm1, hi_m = tm0 < tm1 ? tm1 : tm0;
                double lo = lo_o > lo_m ? lo_o : lo_m, hi = hi_o < hi_m ? hi_o : hi_m;
                double gap = -(hi - lo);
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
    for (int k = 0; k < n_buf; k++) PyBuffer_Release(all[k]);
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
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "Compiled kernels of the SLAM's hot loops (see kernels.py).", -1, methods};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
