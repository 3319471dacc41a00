/* The end of core/sampling.py's prepare() for one cloud: normalisation to the unit sphere and
 * the optional yaw alignment, in double like sampling.normalize and sampling.canonical_yaw
 * (their numpy forms stay the reference). Built exact (no fast-math, no contraction:
 * SOURCE_FLAGS), so every operation rounds as written.
 *
 * normalize: the same operations in the same order as numpy's (column sums in row order,
 * squared radii ((x^2 + y^2) + z^2)), so the same bits. canonical_yaw: numpy takes the
 * covariance from a BLAS dot and its eigenvector from LAPACK; here both are in closed form,
 * so an output may differ by a float32 rounding (test_sampling.py bounds it).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "pgn_geom.h"

/* numpy's pairwise summation of n doubles (stride 1), as its mean over a contiguous axis */
static double pairwise_sum(const double *a, int64_t n) {
    if (n < 8) {
        double r = 0.0;
        for (int64_t i = 0; i < n; ++i) r += a[i];
        return r;
    }
    if (n <= 128) {
        double r[8];
        for (int k = 0; k < 8; ++k) r[k] = a[k];
        int64_t i = 8;
        for (; i < n - n % 8; i += 8)
            for (int k = 0; k < 8; ++k) r[k] += a[i + k];
        double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; ++i) res += a[i];
        return res;
    }
    int64_t n2 = n / 2;
    n2 -= n2 % 8;
    return pairwise_sum(a, n2) + pairwise_sum(a + n2, n - n2);
}

/* xyz (n, 3) float32 -> out (n, 3) float32 centred on the mean, scaled into the unit
 * sphere (a cloud of identical points maps to the origin). */
void pgn_normalize(const float *xyz, int64_t n, float *out) {
    double m[3] = {0.0, 0.0, 0.0};
    for (int64_t i = 0; i < n; ++i)
        for (int a = 0; a < 3; ++a) m[a] += (double)xyz[3 * i + a];
    for (int a = 0; a < 3; ++a) m[a] /= (double)n;
    double r2 = -INFINITY;
    for (int64_t i = 0; i < n; ++i) {
        const double x = (double)xyz[3 * i] - m[0], y = (double)xyz[3 * i + 1] - m[1];
        const double z = (double)xyz[3 * i + 2] - m[2];
        const double s = (x * x + y * y) + z * z;
        r2 = s > r2 || isnan(s) ? s : r2;  /* np.max propagates NaN */
    }
    const double radius = sqrt(r2);
    const int scale = radius > 1e-12 && isfinite(radius);
    for (int64_t i = 0; i < n; ++i)
        for (int a = 0; a < 3; ++a) {
            const double c = (double)xyz[3 * i + a] - m[a];
            out[3 * i + a] = (float)(scale ? c / radius : c * 0.0);
        }
}

/* xyz (n, 3) float32, centred -> out (n, 3) float32: rotated about z so that the major
 * axis of the x-y spread is +x, the signs of x and y fixed by their third moments.
 * dx, dy: n doubles of scratch each. */
void pgn_canonical_yaw(const float *xyz, int64_t n, float *out, double *dx, double *dy) {
    double a = 1.0, b = 0.0, d = 1.0;  /* covariance [[a, b], [b, d]]; one point: identity */
    if (n > 1) {
        for (int64_t i = 0; i < n; ++i) {
            dx[i] = (double)xyz[3 * i];
            dy[i] = (double)xyz[3 * i + 1];
        }
        const double mx = pairwise_sum(dx, n) / (double)n, my = pairwise_sum(dy, n) / (double)n;
        double sxx = 0.0, sxy = 0.0, syy = 0.0;
        for (int64_t i = 0; i < n; ++i) {
            const double u = dx[i] - mx, v = dy[i] - my;
            sxx += u * u; sxy += u * v; syy += v * v;
        }
        const double f = 1.0 / (double)(n - 1);
        a = sxx * f; b = sxy * f; d = syy * f;
    }
    /* eigenvector of the larger eigenvalue; with b = 0 the axis LAPACK's ascending order
     * gives (y on a tie) */
    double c, s;
    if (b == 0.0) {
        c = a > d ? 1.0 : 0.0;
        s = a > d ? 0.0 : 1.0;
    } else {
        const double h = 0.5 * (a - d), lam = 0.5 * (a + d) + sqrt(h * h + b * b);
        double vx = a >= d ? lam - d : b, vy = a >= d ? b : lam - a;
        const double nv = sqrt(vx * vx + vy * vy);
        c = vx / nv;
        s = vy / nv;
    }
    double m3x = 0.0, m3y = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        const double x = (double)xyz[3 * i], y = (double)xyz[3 * i + 1];
        const double xr = x * c + y * s, yr = x * -s + y * c;
        dx[i] = xr;
        dy[i] = yr;
        m3x += copysign(pow(fabs(xr), 3.0), xr);
        m3y += copysign(pow(fabs(yr), 3.0), yr);
    }
    const double sx = m3x < 0.0 ? -1.0 : 1.0, sy = m3y < 0.0 ? -1.0 : 1.0;
    for (int64_t i = 0; i < n; ++i) {
        out[3 * i] = (float)(dx[i] * sx);
        out[3 * i + 1] = (float)(dy[i] * sy);
        out[3 * i + 2] = xyz[3 * i + 2];
    }
}

/* ---- sampling.canonical_order and midpoint_fill's neighbours ---- */

/* A float's bits as an unsigned key that orders like the value; -0 as +0 (they compare
 * equal, so a stable sort keeps their order). */
static inline uint32_t order_key(float f) {
    f = f + 0.0f;  /* -0 + 0 = +0 */
    uint32_t u;
    memcpy(&u, &f, 4);
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

/* idx (n,) int64 = numpy's lexsort((z, y, x)) of xyz (n, 3) float32, finite: by x, then y,
 * then z, ties in input order. Stable LSD radix sort, 8 bits a pass (passes whose digit is
 * the same for every point are skipped). Returns 0, or -1 when out of memory. */
int pgn_canonical_order(const float *xyz, int64_t n, int64_t *idx) {
    uint32_t *key = malloc(sizeof(uint32_t) * (size_t)(n > 0 ? n : 1));
    int64_t *tmp = malloc(sizeof(int64_t) * (size_t)(n > 0 ? n : 1));
    if (!key || !tmp) {
        free(key);
        free(tmp);
        return -1;
    }
    for (int64_t i = 0; i < n; ++i) idx[i] = i;
    for (int a = 2; a >= 0; --a) {  /* least significant key first */
        for (int64_t i = 0; i < n; ++i) key[i] = order_key(xyz[3 * i + a]);
        for (int shift = 0; shift < 32; shift += 8) {
            int64_t cnt[257] = {0};
            for (int64_t i = 0; i < n; ++i) cnt[((key[idx[i]] >> shift) & 0xFFu) + 1]++;
            int same = 0;
            for (int b = 1; b <= 256; ++b) same |= cnt[b] == n;
            if (same) continue;
            for (int b = 0; b < 256; ++b) cnt[b + 1] += cnt[b];
            for (int64_t i = 0; i < n; ++i) tmp[cnt[(key[idx[i]] >> shift) & 0xFFu]++] = idx[i];
            memcpy(idx, tmp, sizeof(int64_t) * (size_t)n);
        }
    }
    free(key);
    free(tmp);
    return 0;
}

/* (dx^2 + dy^2) + dz^2 in double from float32 points: each square is exact */
static inline double dist2_d(const float *p, const float *q) {
    const double dx = (double)p[0] - (double)q[0], dy = (double)p[1] - (double)q[1];
    const double dz = (double)p[2] - (double)q[2];
    return (dx * dx + dy * dy) + dz * dz;
}

/* midpoint_fill's neighbours: for each of the n points of xyz (n, 3) float32, finite and
 * below 1e18 in magnitude, its k + 1 nearest points by (squared distance in double, index)
 * without the first (the point itself, or an exact copy of it) -> nb (n, k) int32, nearest
 * first; 1 <= k < n. The float kNN (pgn_knn) gives k + 2 candidates; float distances are
 * within 1e-6 of the double ones, so while the (k + 1)-th double distance stays below the
 * candidates' largest float distance by that margin, no other point can enter, and the
 * candidates' double order is exact. Otherwise (near ties) the row takes every point within
 * the margin. Returns 0, or -1 when out of memory. */
int pgn_midpoint_neighbours(const float *xyz, int64_t n, int64_t k, int32_t *nb) {
    const int64_t k1 = k + 1, k2 = k + 2 < n ? k + 2 : n;
    float *soa = malloc(sizeof(float) * (size_t)(4 * n));
    uint64_t *keys = malloc(sizeof(uint64_t) * (size_t)(2 * n + 32));
    int32_t *cand = malloc(sizeof(int32_t) * (size_t)(n * k2 + 16));
    int64_t *ck = malloc(sizeof(int64_t) * (size_t)n);
    double *cd = malloc(sizeof(double) * (size_t)n);
    if (!soa || !keys || !cand || !ck || !cd) {
        free(soa);
        free(keys);
        free(cand);
        free(ck);
        free(cd);
        return -1;
    }
    float *x = soa, *y = soa + n, *z = soa + 2 * n, *dist = soa + 3 * n;
    for (int64_t i = 0; i < n; ++i) {
        x[i] = xyz[3 * i];
        y[i] = xyz[3 * i + 1];
        z[i] = xyz[3 * i + 2];
    }
    pgn_knn(x, y, z, n, x, y, z, n, k2, cand, dist, keys, 0.0f);
    for (int64_t i = 0; i < n; ++i) {
        const float *p = xyz + 3 * i;
        float fmax = 0.0f;
        int64_t m = k2;
        for (int64_t j = 0; j < k2; ++j) {
            const float *q = xyz + 3 * (int64_t)cand[i * k2 + j];
            const float dx = p[0] - q[0], dy = p[1] - q[1], dz = p[2] - q[2];
            const float d = (dx * dx + dy * dy) + dz * dz;
            fmax = d > fmax ? d : fmax;
            ck[j] = cand[i * k2 + j];
            cd[j] = dist2_d(p, q);
        }
        for (int pass = 0; pass < 2; ++pass) {
            /* the k + 1 smallest by (double distance, index), in order: selection */
            for (int64_t t = 0; t < k1 && t < m; ++t) {
                int64_t b = t;
                for (int64_t u = t + 1; u < m; ++u)
                    if (cd[u] < cd[b] || (cd[u] == cd[b] && ck[u] < ck[b])) b = u;
                const double td = cd[t];
                const int64_t tk = ck[t];
                cd[t] = cd[b]; ck[t] = ck[b];
                cd[b] = td; ck[b] = tk;
            }
            /* points outside the candidates are at least fmax away in float */
            if (pass || k2 == n || (fmax > 1e-30f && cd[k1 - 1] * (1.0 + 4e-6) < (double)fmax))
                break;
            const double lim = cd[k1 - 1] * (1.0 + 4e-6) + 1e-300;
            m = 0;
            for (int64_t j = 0; j < n; ++j) {  /* near ties: every point within the margin */
                const double d = dist2_d(p, xyz + 3 * j);
                if (d <= lim) { cd[m] = d; ck[m++] = j; }
            }
        }
        for (int64_t t = 1; t < k1; ++t) nb[i * k + t - 1] = (int32_t)ck[t];
    }
    free(soa);
    free(keys);
    free(cand);
    free(ck);
    free(cd);
    return 0;
}
