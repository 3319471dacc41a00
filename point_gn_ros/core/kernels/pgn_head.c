/* One query through a bank section's head (bank/lone.py): the lone query's path.
 *
 * The torch path (bank/head.py, bank/classifier.py) runs ~40 small ops per query; after a
 * sensor's idle gap each one starts with its code and data out of cache, and the section
 * took 2-2.5x its back-to-back time. Here the same formulas run in two calls around the
 * search (bank_dots or the index's candidates):
 *
 * pgn_head_embed: x (D) raw features -> xs (D) = normalize((x - mean) / scale),
 *   z (d) = normalize(((x - mean) / scale) @ P)  (P (D, d) row-major; NULL: z = xs),
 *   u (d) = normalize(z @ W)                    (W (d, d);           NULL: u = z).
 * pgn_head_finish: the cosines of the entries that vote -> calibrated probabilities (C):
 *   log vote shares (each entry at least exp(-80) of the best one's vote, every entry not
 *   among sims counted at that floor, -inf for classes without entries), + ridge_weight x
 *   kernel ridge scores, + the vote bias, + fusion_weight x LDA log-posteriors, softmax / T.
 * pgn_head_linear: out (C) = coef (C, dim) @ in + bias (the gate's two logits).
 *
 * Sums run in double; the results agree with the torch path to ~1e-7 (test_lone_head.py).
 * No fast-math: -inf marks absent classes and must propagate.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define LOGIT_FLOOR (-80.0)

/* v (n) /= max(||v||, 1e-12), as torch.nn.functional.normalize */
static void normalize(float *v, int64_t n) {
    double s = 0.0;
    for (int64_t i = 0; i < n; ++i) s += (double)v[i] * v[i];
    const float norm = (float)sqrt(s);
    const float den = norm > 1e-12f ? norm : 1e-12f;
    for (int64_t i = 0; i < n; ++i) v[i] /= den;
}

/* out (d) = v (D) @ M (D, d), float32 rows accumulated in float32 lanes (M streamed once) */
static void row_times(const float *v, int64_t D, const float *M, int64_t d, float *out) {
    memset(out, 0, (size_t)d * sizeof(float));
    for (int64_t i = 0; i < D; ++i) {
        const float a = v[i];
        const float *m = M + i * d;
        for (int64_t j = 0; j < d; ++j) out[j] += a * m[j];
    }
}

void pgn_head_embed(const float *x, int64_t D, const float *mean, const float *scale,
                    const float *P, int64_t d, const float *W, float *xs, float *z,
                    float *u) {
    for (int64_t i = 0; i < D; ++i) xs[i] = (x[i] - mean[i]) / scale[i];
    if (P != NULL) row_times(xs, D, P, d, z);
    normalize(xs, D);
    if (P == NULL) memcpy(z, xs, (size_t)D * sizeof(float));
    else normalize(z, d);
    if (W != NULL) {
        row_times(z, d, W, d, u);
        normalize(u, d);
    } else {
        memcpy(u, z, (size_t)d * sizeof(float));
    }
}

void pgn_head_linear(const float *in, int64_t dim, const float *coef, int64_t C,
                     const float *bias, double *out) {
    for (int64_t c = 0; c < C; ++c) {
        const float *w = coef + c * dim;
        double s = 0.0;
        for (int64_t j = 0; j < dim; ++j) s += (double)w[j] * in[j];
        out[c] = s + bias[c];
    }
}

/* v (C) -= logsumexp over its finite entries (all -inf: left as is) */
static void log_normalize(double *v, int64_t C) {
    double top = -INFINITY;
    for (int64_t c = 0; c < C; ++c) if (v[c] > top) top = v[c];
    if (!isfinite(top)) return;
    double s = 0.0;
    for (int64_t c = 0; c < C; ++c) s += exp(v[c] - top);
    const double lse = top + log(s);
    for (int64_t c = 0; c < C; ++c) v[c] -= lse;
}

/* sims (M) with labels (M) in [0, C); counts (C) entries per class in the section;
 * ridge_coef (M, C) float32 or NULL (then M is the whole section, in its row order);
 * vote_bias (C) or NULL; lda_coef (C, lda_dim) or NULL; work: 3 C doubles.
 * -> prob (C) float32, *novelty = max(1 - best cosine, 0). Returns 0, or -1 for M < 1. */
int pgn_head_finish(const float *sims, const int64_t *labels, int64_t M, int64_t C,
                    const int64_t *counts, double gamma,
                    const float *ridge_coef, double ridge_gamma, double ridge_weight,
                    const float *vote_bias,
                    const float *lda_in, int64_t lda_dim, const float *lda_coef,
                    const float *lda_bias, double fusion_weight, double temperature,
                    double *work, float *prob, float *novelty) {
    if (M < 1) return -1;
    double *votes = work, *fused = work + C, *aux = work + 2 * C;
    float best = sims[0];
    for (int64_t i = 1; i < M; ++i) if (sims[i] > best) best = sims[i];
    /* the torch path's float32 logits: (s - 1) * gamma, relative to the best entry's */
    const float g = (float)gamma, top = (best - 1.0f) * g;
    memset(votes, 0, (size_t)C * sizeof(double));
    int64_t *seen = (int64_t *)aux;              /* aux reused below, after the votes */
    memset(seen, 0, (size_t)C * sizeof(int64_t));
    for (int64_t i = 0; i < M; ++i) {
        float l = (sims[i] - 1.0f) * g - top;
        if (l < (float)LOGIT_FLOOR) l = (float)LOGIT_FLOOR;
        votes[labels[i]] += (double)expf(l);
        seen[labels[i]] += 1;
    }
    const double floor_vote = exp(LOGIT_FLOOR);
    for (int64_t c = 0; c < C; ++c) {
        const double v = votes[c] + (double)(counts[c] - seen[c]) * floor_vote;
        fused[c] = counts[c] > 0 ? log(v > 1.1754943508222875e-38 ? v : 1.1754943508222875e-38)
                                 : -INFINITY;
    }
    log_normalize(fused, C);
    if (ridge_coef != NULL && ridge_weight != 0.0) {
        memset(aux, 0, (size_t)C * sizeof(double));
        for (int64_t i = 0; i < M; ++i) {
            const double k = exp(ridge_gamma * ((double)sims[i] - 1.0));
            const float *a = ridge_coef + i * C;
            for (int64_t c = 0; c < C; ++c) aux[c] += k * a[c];
        }
        for (int64_t c = 0; c < C; ++c) fused[c] += ridge_weight * (double)(float)aux[c];
    }
    if (vote_bias != NULL)
        for (int64_t c = 0; c < C; ++c) fused[c] += vote_bias[c];
    if (lda_coef != NULL && fusion_weight != 0.0) {
        pgn_head_linear(lda_in, lda_dim, lda_coef, C, lda_bias, aux);
        log_normalize(aux, C);
        for (int64_t c = 0; c < C; ++c) fused[c] += fusion_weight * aux[c];
    }
    for (int64_t c = 0; c < C; ++c) fused[c] /= temperature;
    log_normalize(fused, C);
    for (int64_t c = 0; c < C; ++c) prob[c] = (float)exp(fused[c]);
    const float nov = 1.0f - best;
    *novelty = nov > 0.0f ? nov : 0.0f;
    return 0;
}
