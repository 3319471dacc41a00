/* The end of core/sampling.py's prepare() for one cloud: normalisation to the unit sphere and
 * the optional yaw alignment, in double like sampling.normalize and sampling.canonical_yaw
 * (their numpy forms stay the reference). Compiled without fast-math and with
 * -ffp-contract=off, so every operation rounds as written.
 *
 * normalize: the same operations in the same order as numpy's (column sums in row order,
 * squared radii ((x^2 + y^2) + z^2)), so the same bits. canonical_yaw: numpy takes the
 * covariance from a BLAS dot and its eigenvector from LAPACK; here both are in closed form,
 * so an output may differ by a float32 rounding (test_sampling.py bounds it).
 */
#include <math.h>
#include <stdint.h>

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
