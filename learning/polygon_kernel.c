/* Intersection over union of every polygon of A with every polygon of B:
 * the algorithm of polygon.py's `intersection_area` (Green's theorem along
 * both boundaries, crossings computed once for both), one pair at a time in
 * double precision. Built by polygon_kernel.py with the system's C compiler
 * and called through ctypes; polygon.py's torch code is the reference and
 * the fallback.
 *
 * a: (P, K, 2) float32, b: (W, L, 2) float32, out: (P, W) float32;
 * shift: the generic offset added to B (polygon.SHIFT).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define MAX_VERTICES 64

static double signed_area(const double *x, const double *y, int n) {
    double s = 0.0;
    for (int i = 0; i < n; ++i) {
        int j = i + 1 == n ? 0 : i + 1;
        s += x[i] * y[j] - x[j] * y[i];
    }
    return 0.5 * s;
}

/* Polygon i of p (n vertices, float32) as doubles, counter-clockwise. */
static double load_ccw(const float *p, int n, double dx, double dy, double *x,
                       double *y) {
    for (int i = 0; i < n; ++i) {
        x[i] = (double)p[2 * i];
        y[i] = (double)p[2 * i + 1];
    }
    double area = signed_area(x, y, n);
    if (area < 0) {
        for (int i = 0; i < n / 2; ++i) {
            double t = x[i];
            x[i] = x[n - 1 - i];
            x[n - 1 - i] = t;
            t = y[i];
            y[i] = y[n - 1 - i];
            y[n - 1 - i] = t;
        }
    }
    for (int i = 0; i < n; ++i) {
        x[i] += dx;
        y[i] += dy;
    }
    return fabs(area);
}

/* Even-odd test of point (px, py) against a polygon. */
static int inside(double px, double py, const double *x, const double *y, int n) {
    int hits = 0;
    for (int i = 0; i < n; ++i) {
        int j = i + 1 == n ? 0 : i + 1;
        double ay = y[i], by = y[j], ax = x[i], bx = x[j];
        if ((ay > py) != (by > py)) {
            double t = (py - ay) / (by == ay ? 1.0 : by - ay);
            if (px < ax + t * (bx - ax)) hits ^= 1;
        }
    }
    return hits;
}

static double intersection(const double *ax, const double *ay, int K,
                           const double *bx, const double *by, int L) {
    double sx[MAX_VERTICES], sy[MAX_VERTICES], ex[MAX_VERTICES], ey[MAX_VERTICES];
    int row[MAX_VERTICES], col[MAX_VERTICES];
    for (int k = 0; k < K; ++k) {
        int n = k + 1 == K ? 0 : k + 1;
        sx[k] = ax[n] - ax[k];
        sy[k] = ay[n] - ay[k];
        row[k] = 0;
    }
    for (int l = 0; l < L; ++l) {
        int n = l + 1 == L ? 0 : l + 1;
        ex[l] = bx[n] - bx[l];
        ey[l] = by[n] - by[l];
        col[l] = 0;
    }
    /* First every edge pair's crossing test, without branches (the
     * compiler vectorises it), then the few pairs that cross. */
    unsigned char hit[MAX_VERTICES * MAX_VERTICES];
    int any = 0;
    for (int k = 0; k < K; ++k) {
        for (int l = 0; l < L; ++l) {
            double denom = sx[k] * ey[l] - sy[k] * ex[l];
            double dx = bx[l] - ax[k], dy = by[l] - ay[k];
            /* t = tn / denom along A's edge, u = un / denom along B's, both
             * in (0, 1), tested before dividing. */
            double tn = dx * ey[l] - dy * ex[l];
            double un = dx * sy[k] - dy * sx[k];
            double sg = copysign(1.0, denom), st = tn * sg, su = un * sg;
            double ad = fabs(denom);
            int h = (st > 0) & (st < ad) & (su > 0) & (su < ad) & (ad >= 1e-12);
            hit[k * L + l] = (unsigned char)h;
            any |= h;
        }
    }
    double crossings = 0.0;
    for (int k = 0; k < K && any; ++k) {
        for (int l = 0; l < L; ++l) {
            if (!hit[k * L + l]) continue;
            double denom = sx[k] * ey[l] - sy[k] * ex[l];
            double dx = bx[l] - ax[k], dy = by[l] - ay[k];
            double t = (dx * ey[l] - dy * ex[l]) / denom;
            double u = (dx * sy[k] - dy * sx[k]) / denom;
            if (!(t > 0 && t < 1 && u > 0 && u < 1)) continue;
            double F = sy[k] * (ax[k] * t + 0.5 * sx[k] * t * t);
            double G = ey[l] * (bx[l] * u + 0.5 * ex[l] * u * u);
            crossings += denom > 0 ? F - G : G - F;
            row[k] += 1;
            col[l] += 1;
        }
    }
    double area = crossings;
    int in_a = inside(ax[0], ay[0], bx, by, L);
    for (int k = 0; k < K; ++k) {
        in_a ^= row[k] & 1;
        if (in_a) area += sy[k] * (ax[k] + 0.5 * sx[k]);
    }
    int in_b = inside(bx[0], by[0], ax, ay, K);
    for (int l = 0; l < L; ++l) {
        in_b ^= col[l] & 1;
        if (in_b) area += ey[l] * (bx[l] + 0.5 * ex[l]);
    }
    return area > 0 ? area : 0.0;
}

int iou_all_pairs(const float *a, int64_t P, int K, const float *b, int64_t W,
                  int L, double shift_x, double shift_y, float *out) {
    if (K > MAX_VERTICES || L > MAX_VERTICES || K < 3 || L < 3) return 1;
    if (P == 0 || W == 0) return 0;
    double *bx = malloc(sizeof(double) * W * L), *by = malloc(sizeof(double) * W * L);
    double *b_area = malloc(sizeof(double) * W);
    if (!bx || !by || !b_area) {
        free(bx);
        free(by);
        free(b_area);
        return 2;
    }
    for (int64_t w = 0; w < W; ++w)
        b_area[w] = load_ccw(b + 2 * L * w, L, shift_x, shift_y, bx + L * w, by + L * w);
    double ax[MAX_VERTICES], ay[MAX_VERTICES];
    for (int64_t p = 0; p < P; ++p) {
        double a_area = load_ccw(a + 2 * K * p, K, 0.0, 0.0, ax, ay);
        for (int64_t w = 0; w < W; ++w) {
            double inter = intersection(ax, ay, K, bx + L * w, by + L * w, L);
            double uni = a_area + b_area[w] - inter;
            /* As torch's clamp_min: a NaN union stays NaN. */
            double den = isnan(uni) ? uni : (uni > 1e-12 ? uni : 1e-12);
            out[p * W + w] = (float)(inter / den);
        }
    }
    free(bx);
    free(by);
    free(b_area);
    return 0;
}
