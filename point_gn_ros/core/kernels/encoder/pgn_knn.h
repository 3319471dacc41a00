/* Shared by the kNN's two files (pgn_knn.c: float distances and the entry points;
 * pgn_knn_codes16.c: 16-bit codes): keys, the middle of a bracket, the next threshold.
 * Both are built exact (no fast-math, no contraction: kernels/__init__.py SOURCE_FLAGS).
 */
#ifndef PGN_KNN_H
#define PGN_KNN_H

#include <stdint.h>
#include <string.h>

#include "pgn_geom.h"

/* Keys sort by (distance, index): distances are >= +0 so their bit patterns
 * order like the values. */
static inline uint64_t make_key(float d, int64_t i) {
    uint32_t b;
    memcpy(&b, &d, 4);
    return ((uint64_t)b << 32) | (uint64_t)(uint32_t)i;
}

/* Partition keys so that keys[0..k) are the k smallest (unordered). */
static inline void select_k(uint64_t *keys, int64_t n, int64_t k) {
    int64_t lo = 0, hi = n - 1;
    while (hi > lo) {
        /* median of three pivot */
        int64_t mid = lo + (hi - lo) / 2;
        uint64_t a = keys[lo], b = keys[mid], c = keys[hi];
        uint64_t p = a < b ? (b < c ? b : (a < c ? c : a)) : (a < c ? a : (b < c ? c : b));
        int64_t i = lo, j = hi;
        while (i <= j) {
            while (keys[i] < p) i++;
            while (keys[j] > p) j--;
            if (i <= j) { uint64_t t = keys[i]; keys[i] = keys[j]; keys[j] = t; i++; j--; }
        }
        if (k - 1 <= j) hi = j;
        else if (k - 1 >= i) lo = i;
        else return;
    }
}


/* The middle of a bracket, mk[0..nm) (keys by distance then index), into out[0..need):
 * the need smallest, unordered. A few by each key's rank among them (keys are distinct):
 * no sort, and a rank at or past need is written one place past out[need - 1] at most. */
static inline void take_middle(uint64_t *mk, int64_t nm, int64_t need, int32_t *out) {
    if (nm <= 32) {
        int64_t w = 0;
        for (int64_t j = 0; j < nm; ++j) {
            int64_t r = 0;
            for (int64_t i = 0; i < nm; ++i) r += mk[i] < mk[j];
            out[w] = (int32_t)(mk[j] & 0xffffffffu);
            w += r < need;
        }
    } else {
        select_k(mk, nm, need);
        for (int64_t j = 0; j < need; ++j) out[j] = (int32_t)(mk[j] & 0xffffffffu);
    }
}

/* The next threshold inside a bracket (lo, hi) of distances (lo < 0: nothing below):
 * interpolated towards count k, never shrinking the bracket by less than 10 %. */
static inline float bracket_tau(float lo, float hi, int64_t clo, int64_t chi, int64_t k) {
    const float base = lo < 0.0f ? 0.0f : lo, w = hi - base;
    float tau = base + w * (float)(((double)k - 0.5 - (double)clo) / (double)(chi - clo));
    if (tau < base + 0.1f * w) tau = base + 0.1f * w;
    if (tau > hi - 0.1f * w) tau = hi - 0.1f * w;
    return tau;
}


#if defined(__AVX512BW__) && defined(__AVX512VBMI2__)
/* pgn_knn_codes16.c: the search on 16-bit codes for centres [0, s) (64 <= n < 65536), in a slab
 * where sl is given. */
void pgn_knn_codes(const float *x, const float *y, const float *z, int64_t n, const float *cx,
                   const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb,
                   float *dist, uint64_t *keys, float guess, const pgn_slab *sl);
#endif

#endif
