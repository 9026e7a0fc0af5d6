/* Compiled kernels of the map server's hot loops and of the scan matcher both sides use (the SLAM's are in robot_agent/slam/_kernels.c):
 * the k nearest points within a distance, for map_server/registration.py's map index (the same
 * answer as scipy's cKDTree.query with distance_upper_bound, ties in distance ordered by index),
 * with what registration computes of each neighbour (facing difference, distance to its line);
 * the merge's collinearity test of segment pairs (map_server/fusion.collinear); and the scan
 * matcher's window sums (shared/scanmatch.py: the agents' loop search and the fleet graph's
 * keyframe-scan constraints).
 * shared/kernels.py wraps it and keeps the k-d tree as the reference and the fallback when this
 * module is not built; tests/map_server/test_server_kernels.py holds both to the same results.
 *
 * Arrays come through the buffer protocol (no numpy headers at build time), C-contiguous,
 * float64 unless said otherwise; each function checks their sizes against the shapes it is
 * given. Built with -ffp-contract=off (no fused multiply-add the reference does not make).
 */
#include "_common.h" /* sizes_ok, release, wrap_angle */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#define MAX_K 64

/* Whether (d2, j) comes before (e2, i): nearer first, the lower index among equals. */
static inline int before(double d2, int64_t j, double e2, int64_t i) { return d2 < e2 || (d2 == e2 && j < i); }

/* The grid's cells [lo, hi] along one axis that points within ``bound`` of ``v`` can lie in,
 * clamped to [0, n): 0 if none. The range is widened by a part in 1e9 of the bound: a point whose
 * computed distance is just below the bound is never in a cell the rounding put outside. */
static int cell_range(double v, double bound, double cell, int64_t origin, int64_t n, int64_t *lo, int64_t *hi) {
    double slack = bound * 1e-9 + 1e-12;
    double a = floor((v - bound - slack) / cell), b = floor((v + bound + slack) / cell);
    if (!(fabs(a) < 4e18 && fabs(b) < 4e18)) return 0; /* not finite */
    int64_t l = (int64_t)a - origin, h = (int64_t)b - origin;
    if (l < 0) l = 0;
    if (h > n - 1) h = n - 1;
    *lo = l;
    *hi = h;
    return l <= h;
}

/* near: for each query point, the k nearest points nearer than ``bound`` (squared distance
 * below bound²), nearest first, the lower index first among equals; missing neighbours get
 * distance inf and index M. The N points come sorted by grid cell: ``data`` (N,S) their rows in
 * that order, x and y first (S >= 2 columns); ``order`` (N,) their indices in [0, M) (points left out of the grid
 * keep theirs); ``start`` (W*H+1,) the first of each cell: cell (cx, cy) is row cx*H + cy relative
 * to the grid's origin cell (x0, y0); a point's cell is floor(x / cell).
 *
 * With ``lines`` (S >= 6) the points are samples of directed lines, each row x, y, facing, unit
 * normal nx, ny and offset (nx x + ny y = offset on the line), and each query has a facing ``qf``
 * (Q,): for every neighbour slot the facing difference |wrap(qf - facing)| and the signed distance
 * of the query to the line nx x + ny y - offset, the slots of missing neighbours with point 0's
 * line ``line0`` (facing, nx, ny, offset), as map_server/registration.py computes them; without,
 * ``qf``, ``line0`` and the two outputs are empty. Returns how many queries lie outside
 * the box lo_x, lo_y, hi_x, hi_y. */
static PyObject *near(PyObject *self, PyObject *args) {
    Py_buffer b_data, b_order, b_start, b_q, b_qf, b_line0, b_d, b_j, b_dang, b_perp;
    Py_ssize_t N, S, M, W, H, Q, K;
    long long x0, y0;
    int lines;
    double cell, bound, lo_x, lo_y, hi_x, hi_y;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*w*w*w*w*nnnnnnnLLddpdddd", &b_data, &b_order, &b_start, &b_q, &b_qf,
                          &b_line0, &b_d, &b_j, &b_dang, &b_perp, &N, &S, &M, &W, &H, &Q, &K, &x0, &y0, &cell,
                          &bound, &lines, &lo_x, &lo_y, &hi_x, &hi_y))
        return NULL;
    Py_buffer *all[] = {&b_data, &b_order, &b_start, &b_q, &b_qf, &b_line0, &b_d, &b_j, &b_dang, &b_perp};
    const int n_buf = (int)(sizeof(all) / sizeof(all[0]));
    PyObject *result = NULL;
    if (N < 0 || S < (lines ? 6 : 2) || M < N || W < 0 || H < 0 || Q < 0 || K < 1 || K > MAX_K ||
        (W > 0 && H > PY_SSIZE_T_MAX / 8 / W)) {
        PyErr_Format(PyExc_ValueError,
                     "near: bad sizes N=%zd S=%zd M=%zd W=%zd H=%zd Q=%zd k=%zd (k in 1..%d; S >= 6 with lines)", N, S,
                     M, W, H, Q, K, MAX_K);
        goto done;
    }
    const Py_ssize_t L = lines ? 1 : 0;
    Py_ssize_t need[] = {N * S * 8, N * 8, (W * H + 1) * 8, Q * 2 * 8, L * Q * 8, L * 4 * 8, Q * K * 8, Q * K * 8,
                         L * Q * K * 8, L * Q * K * 8};
    if (!sizes_ok("near", all, need, n_buf)) goto done;
    if (!(cell > 0.0) || !isfinite(cell) || !(bound >= 0.0)) {
        PyErr_Format(PyExc_ValueError, "near: cell must be finite and > 0 (got %g), bound >= 0 (got %g)", cell, bound);
        goto done;
    }
    const double *data = b_data.buf, *q = b_q.buf, *qf = b_qf.buf, *line0 = b_line0.buf;
    const int64_t *order = b_order.buf, *start = b_start.buf;
    double *d_out = b_d.buf, *dang_out = b_dang.buf, *perp_out = b_perp.buf;
    int64_t *j_out = b_j.buf;
    double b2 = bound * bound;
    Py_ssize_t outside = 0;
    int bad = 0; /* a grid the queries cannot trust: a run of cells outside [0, N), an index outside [0, M) */
    Py_BEGIN_ALLOW_THREADS
    double bd[MAX_K];
    int64_t bj[MAX_K];
    Py_ssize_t bi[MAX_K]; /* their rows in data */
    for (Py_ssize_t k = 0; k < Q; k++) {
        double x = q[2 * k], y = q[2 * k + 1];
        outside += x < lo_x || y < lo_y || x > hi_x || y > hi_y;
        Py_ssize_t m = 0; /* neighbours held, nearest first */
        int64_t gx0, gx1, gy0, gy1;
        if (W > 0 && cell_range(x, bound, cell, x0, W, &gx0, &gx1) && cell_range(y, bound, cell, y0, H, &gy0, &gy1)) {
            for (int64_t gx = gx0; gx <= gx1; gx++) {
                /* the cells (gx, gy0..gy1) are one run of points */
                Py_ssize_t from = start[gx * H + gy0], to = start[gx * H + gy1 + 1];
                if (from < 0 || to > N || from > to) {
                    bad = 1;
                    break;
                }
                for (Py_ssize_t i = from; i < to; i++) {
                    double dx = data[S * i] - x, dy = data[S * i + 1] - y;
                    double d2 = dx * dx + dy * dy;
                    if (!(d2 < b2)) continue;
                    int64_t j = order[i];
                    if (j < 0 || j >= M) {
                        bad = 1;
                        break;
                    }
                    if (m == K && !before(d2, j, bd[K - 1], bj[K - 1])) continue;
                    Py_ssize_t at = m < K ? m++ : K - 1; /* insert, the last one falling off when full */
                    while (at > 0 && before(d2, j, bd[at - 1], bj[at - 1])) {
                        bd[at] = bd[at - 1];
                        bj[at] = bj[at - 1];
                        bi[at] = bi[at - 1];
                        at--;
                    }
                    bd[at] = d2;
                    bj[at] = j;
                    bi[at] = i;
                }
            }
        }
        double *d = d_out + k * K;
        int64_t *jo = j_out + k * K;
        for (Py_ssize_t a = 0; a < m; a++) {
            d[a] = sqrt(bd[a]);
            jo[a] = bj[a];
        }
        for (Py_ssize_t a = m; a < K; a++) {
            d[a] = INFINITY;
            jo[a] = M;
        }
        if (lines) {
            double *dang = dang_out + k * K, *perp = perp_out + k * K;
            for (Py_ssize_t a = 0; a < m; a++) {
                const double *r = data + S * bi[a];
                dang[a] = fabs(wrap_angle(qf[k] - r[2]));
                perp[a] = r[3] * x + r[4] * y - r[5];
            }
            if (m < K) {
                double dang0 = fabs(wrap_angle(qf[k] - line0[0])), perp0 = line0[1] * x + line0[2] * y - line0[3];
                for (Py_ssize_t a = m; a < K; a++) {
                    dang[a] = dang0;
                    perp[a] = perp0;
                }
            }
        }
    }
    Py_END_ALLOW_THREADS
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "near: the grid's starts must rise within [0, N], its order lie in [0, M)");
        goto done;
    }
    result = PyLong_FromSsize_t(outside);
done:
    release(all, n_buf);
    return result;
}

/* grid: the points' cell order for ``near``. ``cols`` (S,N) holds each point's values column by
 * column, x and y first; a point whose x or y is not finite is left out. Writes the kept points'
 * rows in cell order to ``data_out`` (N,S) and their indices to ``order_out`` (N,) — a stable
 * counting sort: within a cell, in index order — and the first of each cell to ``start_out``
 * (W*H+1,) (cell (cx, cy), cx = floor(x / cell) - x0, is row cx*H + cy); returns how many were
 * kept. Every kept point's cell must lie within the W x H grid (the caller's extent). */
static PyObject *grid(PyObject *self, PyObject *args) {
    Py_buffer b_cols, b_data, b_order, b_start;
    Py_ssize_t S, N, W, H;
    long long x0, y0;
    double cell;
    if (!PyArg_ParseTuple(args, "y*w*w*w*nnnnLLd", &b_cols, &b_data, &b_order, &b_start, &S, &N, &W, &H, &x0, &y0,
                          &cell))
        return NULL;
    Py_buffer *all[] = {&b_cols, &b_data, &b_order, &b_start};
    const int n_buf = (int)(sizeof(all) / sizeof(all[0]));
    PyObject *result = NULL;
    int64_t *cellof = NULL;
    if (S < 2 || N < 0 || W < 0 || H < 0 || (W > 0 && H > PY_SSIZE_T_MAX / 8 / W) || !(cell > 0.0) || !isfinite(cell)) {
        PyErr_Format(PyExc_ValueError, "grid: bad sizes S=%zd N=%zd W=%zd H=%zd or cell %g", S, N, W, H, cell);
        goto done;
    }
    Py_ssize_t need[] = {S * N * 8, N * S * 8, N * 8, (W * H + 1) * 8};
    if (!sizes_ok("grid", all, need, n_buf)) goto done;
    const double *cols = b_cols.buf;
    double *data = b_data.buf;
    int64_t *order = b_order.buf, *start = b_start.buf;
    cellof = malloc(sizeof(int64_t) * (size_t)(N > 0 ? N : 1));
    if (!cellof) {
        PyErr_NoMemory();
        goto done;
    }
    int outside = 0;
    Py_ssize_t kept = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t c = 0; c <= W * H; c++) start[c] = 0;
    for (Py_ssize_t i = 0; i < N; i++) {
        double x = cols[i], y = cols[N + i];
        cellof[i] = -1;
        if (!(isfinite(x) && isfinite(y))) continue;
        double fx = floor(x / cell) - (double)x0, fy = floor(y / cell) - (double)y0;
        if (!(fx >= 0.0 && fx < (double)W && fy >= 0.0 && fy < (double)H)) {
            outside = 1;
            break;
        }
        cellof[i] = (int64_t)fx * H + (int64_t)fy;
        start[cellof[i] + 1]++;
        kept++;
    }
    if (!outside) {
        for (Py_ssize_t c = 0; c < W * H; c++) start[c + 1] += start[c];
        for (Py_ssize_t i = 0; i < N; i++) { /* start[c] counts up to the end of cell c meanwhile */
            if (cellof[i] < 0) continue;
            Py_ssize_t at = start[cellof[i]]++;
            order[at] = i;
            for (Py_ssize_t k = 0; k < S; k++) data[at * S + k] = cols[k * N + i];
        }
        for (Py_ssize_t c = W * H; c > 0; c--) start[c] = start[c - 1]; /* back to the first of each */
        start[0] = 0;
    }
    Py_END_ALLOW_THREADS
    if (outside) {
        PyErr_SetString(PyExc_ValueError, "grid: a point lies outside the grid's extent");
        goto done;
    }
    result = PyLong_FromSsize_t(kept);
done:
    free(cellof);
    release(all, n_buf);
    return result;
}

/* collinear: whether segments i[k] and j[k] of ``seg`` (N,2,2) are one wall
 * (map_server/fusion.collinear, the same arithmetic): a = the longer one (of equal ones the first
 * by coordinates), b = the shorter; b's direction within the angle (cos_ab >= cos_min), b's ends
 * within perp_max of a's line, and the gap along a at most gap_max. A pair with a coordinate
 * that is not finite is not one wall. */
static PyObject *collinear(PyObject *self, PyObject *args) {
    Py_buffer b_seg, b_i, b_j, b_ok;
    Py_ssize_t N, K;
    double cos_min, perp_max, gap_max;
    if (!PyArg_ParseTuple(args, "y*y*y*w*nnddd", &b_seg, &b_i, &b_j, &b_ok, &N, &K, &cos_min, &perp_max, &gap_max))
        return NULL;
    Py_buffer *all[] = {&b_seg, &b_i, &b_j, &b_ok};
    const int n_buf = (int)(sizeof(all) / sizeof(all[0]));
    PyObject *result = NULL;
    if (N < 0 || K < 0) {
        PyErr_Format(PyExc_ValueError, "collinear: bad sizes N=%zd K=%zd", N, K);
        goto done;
    }
    Py_ssize_t need[] = {N * 4 * 8, K * 8, K * 8, K};
    if (!sizes_ok("collinear", all, need, n_buf)) goto done;
    const double *seg = b_seg.buf;
    const int64_t *ii = b_i.buf, *jj = b_j.buf;
    uint8_t *ok = b_ok.buf;
    for (Py_ssize_t k = 0; k < K; k++) {
        if (ii[k] < 0 || ii[k] >= N || jj[k] < 0 || jj[k] >= N) {
            PyErr_Format(PyExc_IndexError, "collinear: pair %zd (%lld, %lld) outside [0, %zd)", k, (long long)ii[k],
                         (long long)jj[k], N);
            goto done;
        }
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < K; k++) {
        const double *si = seg + 4 * ii[k], *sj = seg + 4 * jj[k];
        int finite = 1;
        for (int c = 0; c < 4; c++) finite &= isfinite(si[c]) && isfinite(sj[c]);
        if (!finite) {
            ok[k] = 0;
            continue;
        }
        double l0 = hypot(si[2] - si[0], si[3] - si[1]), l1 = hypot(sj[2] - sj[0], sj[3] - sj[1]);
        int swap = l1 > l0;
        if (l1 == l0) { /* of equal ones the first by coordinates */
            swap = 0;
            for (int c = 0; c < 4; c++) {
                double d = sj[c] - si[c];
                if (d != 0.0) {
                    swap = d < 0.0;
                    break;
                }
            }
        }
        const double *a = swap ? sj : si, *b = swap ? si : sj;
        double la_raw = swap ? l1 : l0, lb = swap ? l0 : l1;
        double la = la_raw > 1e-12 ? la_raw : 1e-12;
        double ux = (a[2] - a[0]) / la, uy = (a[3] - a[1]) / la;
        double r0x = b[0] - a[0], r0y = b[1] - a[1], r1x = b[2] - a[0], r1y = b[3] - a[1];
        double t0 = r0x * ux + r0y * uy, t1 = r1x * ux + r1y * uy;
        double p0 = fabs(ux * r0y - uy * r0x), p1 = fabs(ux * r1y - uy * r1x);
        double cos_ab = (ux * (b[2] - b[0]) + uy * (b[3] - b[1])) / (lb > 1e-12 ? lb : 1e-12);
        double tmin = t0 < t1 ? t0 : t1, tmax = t0 > t1 ? t0 : t1;
        double g0 = tmin - la, g1 = -tmax;
        double gap = g0 > g1 ? g0 : g1;
        ok[k] = cos_ab >= cos_min && (p0 > p1 ? p0 : p1) <= perp_max && gap <= gap_max;
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

/* ---- scan matching (shared/scanmatch.py) ------------------------------------------------------------ */

/* scanmatch.window_scores' inner sums: out[a, t] = mean over n of values[cells[a, n] + (ox, oy)[t]],
 * 0 outside the (W, H) grid. */
static PyObject *window_sums(PyObject *self, PyObject *args) {
    Py_buffer b_v, b_c, b_ox, b_oy, b_out;
    Py_ssize_t W, H, A, N, T;
    if (!PyArg_ParseTuple(args, "y*y*y*y*w*nnnnn", &b_v, &b_c, &b_ox, &b_oy, &b_out, &W, &H, &A, &N, &T))
        return NULL;
    Py_buffer *all[] = {&b_v, &b_c, &b_ox, &b_oy, &b_out};
    Py_ssize_t need[] = {W * H * 8, A * N * 2 * 8, T * 8, T * 8, A * T * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("window_sums", all, need, n_buf)) goto done;
    const double *v = b_v.buf;
    const int64_t *cells = b_c.buf, *ox = b_ox.buf, *oy = b_oy.buf;
    double *out = b_out.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t a = 0; a < A; a++) {
        const int64_t *c = cells + 2 * N * a;
        for (Py_ssize_t t = 0; t < T; t++) {
            double sum = 0.0;
            for (Py_ssize_t n = 0; n < N; n++) {
                int64_t ix = c[2 * n] + ox[t], iy = c[2 * n + 1] + oy[t];
                if (ix >= 0 && ix < W && iy >= 0 && iy < H) sum += v[ix * H + iy];
            }
            out[a * T + t] = N > 0 ? sum / (double)N : NAN;
        }
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

/* scanmatch.branch_and_bound's scores without padding: out[m] = mean over n of
 * level[cells[a[m], n] + (ox[m], oy[m])], 0 off the (W, H) float32 grid. */
static PyObject *block_sums(PyObject *self, PyObject *args) {
    Py_buffer b_l, b_c, b_a, b_ox, b_oy, b_out;
    Py_ssize_t W, H, A, N, M;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*nnnnn", &b_l, &b_c, &b_a, &b_ox, &b_oy, &b_out, &W, &H, &A, &N, &M))
        return NULL;
    Py_buffer *all[] = {&b_l, &b_c, &b_a, &b_ox, &b_oy, &b_out};
    Py_ssize_t need[] = {W * H * 4, A * N * 2 * 8, M * 8, M * 8, M * 8, M * 8};
    const int n_buf = (int)(sizeof(need) / sizeof(need[0]));
    PyObject *result = NULL;
    if (!sizes_ok("block_sums", all, need, n_buf)) goto done;
    const float *level = b_l.buf;
    const int64_t *cells = b_c.buf, *am = b_a.buf, *ox = b_ox.buf, *oy = b_oy.buf;
    double *out = b_out.buf;
    for (Py_ssize_t m = 0; m < M; m++) {
        if (am[m] < 0 || am[m] >= A) {
            PyErr_Format(PyExc_IndexError, "block_sums: angle %lld of %zd", (long long)am[m], A);
            goto done;
        }
    }
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t m = 0; m < M; m++) {
        const int64_t *c = cells + 2 * N * am[m];
        int64_t dx = ox[m], dy = oy[m];
        double sum = 0.0;
        for (Py_ssize_t n = 0; n < N; n++) {
            int64_t ix = c[2 * n] + dx, iy = c[2 * n + 1] + dy;
            if (ix >= 0 && ix < W && iy >= 0 && iy < H) sum += level[ix * H + iy];
        }
        out[m] = sum / (double)(N > 0 ? N : 1);
    }
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
done:
    release(all, n_buf);
    return result;
}

static PyMethodDef methods[] = {
    {"near", near, METH_VARARGS,
     "near(data, order, start, q, qf, line0, d_out, j_out, dang_out, perp_out, N, S, M, W, H, Q, k, x0, y0, "
     "cell, bound, lines, lo_x, lo_y, hi_x, hi_y) -> outside: the k nearest points within bound of each query "
     "(cKDTree.query's answer, ties by index), with lines their facing differences and line distances."},
    {"grid", grid, METH_VARARGS,
     "grid(cols, data_out, order_out, start_out, S, N, W, H, x0, y0, cell) -> kept: the points in cell order "
     "for near()."},
    {"collinear", collinear, METH_VARARGS,
     "collinear(seg, i, j, ok_out, N, K, cos_min, perp_max, gap_max): map_server/fusion.collinear's mask."},
    {"window_sums", window_sums, METH_VARARGS,
     "window_sums(values, cells, ox, oy, out, W, H, A, N, T): scanmatch.window_scores' mean likelihoods."},
    {"block_sums", block_sums, METH_VARARGS,
     "block_sums(level, cells, a, ox, oy, out, W, H, A, N, M): branch_and_bound's scores, no padding."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "Compiled kernels of the map server (see shared/kernels.py).", -1, methods};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
