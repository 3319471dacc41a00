/* A stage's kernel plan, fixed by its grid of Gaussian centres and q alone: whether the
 * separable form (sep_t) is safe and with which blocks (pgn_sep_plan, from pgn_encode.c),
 * and the neighbour-lanes kernels' blocks and per-channel factors (lanes_t).
 */
#include "pgn_common.h"

#if defined(__AVX512F__) || defined(PGN_AVX2)
/* Whether a separable kernel that folds T out of its products (w = T^2 (f / T + A e) A e)
 * keeps T^2 in float range for blocks of L + 1: |log T_l| <= 2 |q| L h + |q| L^2 h^2 < 40. */
static int tfold_ok(int64_t nc, double q, int L) {
    const double h = 2.0 / (double)(nc + 1), aq = fabs(q);
    return 2.0 * aq * L * h + aq * L * L * h * h < 40.0;
}

/* Whether sep_t's chained A (blocks of B) stays in float range and loses nothing that
 * matters: the factors P^B and C_m within e^+-80, and where some A_m underflows (|b_m - w|
 * > sqrt(87 / |q|), so |w| > sqrt(87 / |q|) - 1) every Gaussian of centres in (-1, 1) is
 * below e^-30, so the zeros the chain carries on lose only such values. */
static int chain_ok(int64_t nc, double q, int B) {
    const double h = 2.0 / (double)(nc + 1), aq = fabs(q), W = 1.0 + sqrt(87.0 / aq);
    const double r = sqrt(87.0 / aq) - 2.0, b = (double)B;
    return 2.0 * b * aq * h * W < 80.0 && 2.0 * b * aq * h + b * b * aq * h * h < 80.0
           && r > 0.0 && aq * r * r > 30.0;
}
#endif

/* The separable form for nc centres per axis at this q: blocks of 16 where the AVX-512 path
 * runs and float range allows, else of 8 (the kernels that fold T out, sep_centre16 and
 * AVX2's sep_pass8, also need tfold_ok); its grid b (M), T (M B) and, where the ISA path
 * chains and chain_ok allows, C (M) filled, from the exact linspace formula in double,
 * rounded once. fx gets all but its A and E scratch. Returns B, or 0 where the form is not
 * used (fx untouched). */
int pgn_sep_plan(int64_t nc, float q, sep_t *fx, float *b, float *C, float *T) {
    int B = 0;
#if defined(__AVX512F__) && defined(__AVX512VL__) && !defined(PGN_NO_SEPARABLE_AVX512)
    if (pgn_sep_ok(nc, (double)q, 16) && tfold_ok(nc, (double)q, 15)) B = 16;
#endif
#if defined(PGN_AVX2)
    if (!B && pgn_sep_ok(nc, (double)q, 8) && tfold_ok(nc, (double)q, 7)) B = 8;
#else
    if (!B && pgn_sep_ok(nc, (double)q, 8)) B = 8;
#endif
    if (!B) return 0;
    const double h = 2.0 / (double)(nc + 1), b0 = -1.0 + h, qd = (double)q;
    fx->n = nc;
    fx->B = B;
    fx->M = (nc + B - 1) / B;
    fx->q = q;
    fx->h2q = (float)(-2.0 * qd * h);
    fx->W = (float)(1.0 + sqrt(87.0 / fabs(qd)));
    for (int64_t m = 0; m < fx->M; ++m) {
        const double bm = b0 + (double)B * (double)m * h;
        b[m] = (float)bm;
        for (int l = 0; l < B; ++l)
            T[m * B + l] = (float)exp(2.0 * qd * l * h * bm + qd * l * l * h * h);
    }
    fx->b = b;
    fx->T = T;
    fx->C = NULL;
    (void)C;
#if (defined(__AVX512F__) || defined(PGN_AVX2)) && !defined(PGN_NO_CHAIN)
    /* the ISA paths that chain: AVX-512 with blocks of 16, AVX2 with blocks of 8 */
#if defined(__AVX512F__)
    const int chain_b = 16;
#else
    const int chain_b = 8;
#endif
    if (B == chain_b && chain_ok(nc, qd, B)) {
        for (int64_t m = 0; m < fx->M; ++m)
            C[m] = (float)exp(2.0 * B * qd * h * (b0 + (double)B * (double)m * h)
                              + (double)(B * B) * qd * h * h);
        fx->C = C;
    }
#endif
    return B;
}

/* Whether separable Gaussians are safe in float for n centres in (-1, 1) and this q
 * (see sep_t), and worth it (n >= SEP_MIN_N). */
int pgn_sep_ok(int64_t n, double q, int B) {
    const double aq = fabs(q), h = 2.0 / (double)(n + 1), W = 1.0 + sqrt(87.0 / aq);
    const double L = (double)(B - 1);  /* largest power of P in a block */
    return n >= SEP_MIN_N && 2.0 * L * aq * h * (1.0 + W) + L * L * aq * h * h < 80.0
           && L * h * sqrt(aq) < 3.8;
}

/* Whether blocks of B Gaussians (L = B - 1 steps of P from A_m) are safe in float for nc
 * centres in (-1, 1) at this q. A step's running product A_m P^l is pe_l / T_l and
 * |log T_l| <= 2 |q| L h + |q| L^2 h^2, kept under 40 so that T^2 (the rescaling) stays in
 * range too; P = exp(-2 q h w) stays in range for |w| <= W. When A_m underflows (|b_m - w| >
 * sqrt(87 / |q|)) the block's largest Gaussian is below exp(-(sqrt(87) - L h sqrt|q|)^2),
 * under e^-30 for L h sqrt|q| < 3.8: only such values are lost. */
static int lanes_range_ok(int64_t nc, double q, int64_t B) {
    const double aq = fabs(q), h = 2.0 / (double)(nc + 1), W = 1.0 + sqrt(87.0 / aq);
    const double L = (double)(B - 1);
    return L * h * sqrt(aq) < 3.8 && 2.0 * aq * L * h + aq * L * L * h * h < 40.0
           && 2.0 * aq * h * W < 80.0;
}

/* Blocks for nc Gaussians per axis at this q: the fewest that pass lanes_range_ok.
 * Fills lp (b: (nblk,) block bases, T: (nc,) T of each centre index j = m B + l); returns
 * 0 when even single Gaussians fail (the caller keeps the channels-in-lanes kernel). */
int pgn_lanes_plan(int64_t nc, float q, lanes_t *lp, float *b, float *T) {
    if (nc < 1 || nc > PGN_LANES_MAXC) return 0;
    const double qd = (double)q, h = 2.0 / (double)(nc + 1), b0 = -1.0 + h;
    for (int64_t nblk = 1; nblk <= nc; ++nblk) {
        const int64_t B = (nc + nblk - 1) / nblk;
        if (!lanes_range_ok(nc, qd, B)) continue;
        lp->nc = nc;
        lp->B = B;
        lp->nblk = (nc + B - 1) / B;
        lp->ql = (float)(-qd * 1.4426950408889634);
        lp->h2ql = (float)(-2.0 * qd * h * 1.4426950408889634);
        lp->W = (float)(1.0 + sqrt(87.0 / fabs(qd)));
        for (int64_t j = 0; j < nc; ++j) {
            const int64_t m = j / B, l = j % B;
            const double bm = b0 + (double)(B * m) * h;
            b[m] = (float)bm;
            T[j] = (float)exp(2.0 * qd * (double)l * h * bm
                              + qd * (double)(l * l) * h * h);
        }
        lp->b = b;
        lp->T = T;
        return 1;
    }
    return 0;
}

/* Floats of scratch the neighbour-lanes kernels (pgn_avx512_neighbour_lanes.c,
 * pgn_avx2_neighbour_lanes.c) need for K neighbours and D <= 32: the (D + 3, Kc) tables, Kc = K rounded up to 128, two rows
 * of Kc (AVX2: a chunk's P and lane masks), 64 channels' lane partials twice, and 4 rows of
 * 64 per-channel values. */
int64_t pgn_lanes_scratch(int64_t K) {
    const int64_t Kc = (K + 127) / 128 * 128;
    return (32 + 5) * Kc + 2 * 64 * 16 + 4 * 64;
}

/* Per-channel factors of the neighbour-lanes kernels for 2D (<= 64) pe channels: with pe =
 * T U the lanes aggregate (f / T + U) U and scale each channel's max and sum by T^2 (T >
 * 0). rs: r / T (the offset half's rows), ct: 1 / T (the centre half's values), t2: T^2;
 * 64 floats each, T = 1 past 2D. */
void pgn_lanes_scales(const lanes_t *lp, int64_t D2, float r, float *rs, float *ct, float *t2) {
    for (int64_t ch = 0; ch < 64; ++ch) {
        const float T = ch < D2 ? lp->T[ch % lp->nc] : 1.0f;
        rs[ch] = r / T;
        ct[ch] = 1.0f / T;
        t2[ch] = T * T;
    }
}
