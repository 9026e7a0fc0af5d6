/* What the project's C extensions (robot_agent/slam/_kernels.c, shared/_kernels.c) share:
 * argument checks (arrays come through the buffer protocol, and each function checks their byte
 * sizes against the shapes it is given before it reads them) and numpy's angle wrap. */
#ifndef FLEET_SLAM_COMMON_H
#define FLEET_SLAM_COMMON_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#define TWO_PI 6.283185307179586

/* numpy's (a + pi) % 2pi - pi (shared/geometry.wrap_angle): floor modulo, the result takes the
 * divisor's sign. fmod(t, 2pi) is t itself for t in [0, 2pi): no call for an angle that needs
 * no wrap. */
static inline double wrap_angle(double a) {
    double t = a + M_PI;
    if (t >= 0.0 && t < TWO_PI) return t - M_PI;
    double r = fmod(t, TWO_PI);
    if (r != 0.0) {
        if (r < 0.0) r += TWO_PI;
    } else {
        r = 0.0;
    }
    return r - M_PI;
}

/* Every buffer holds the bytes its shape says, else a ValueError naming the argument: 1 if so. */
static int sizes_ok(const char *name, Py_buffer *const *all, const Py_ssize_t *need, int n) {
    for (int k = 0; k < n; k++) {
        if (all[k]->len != need[k]) {
            PyErr_Format(PyExc_ValueError, "%s: argument %d holds %zd bytes, expected %zd", name, k, all[k]->len,
                         need[k]);
            return 0;
        }
    }
    return 1;
}

static void release(Py_buffer *const *all, int n) {
    for (int k = 0; k < n; k++) PyBuffer_Release(all[k]);
}

#endif
