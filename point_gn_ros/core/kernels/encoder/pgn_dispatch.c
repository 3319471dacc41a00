/* The encoder's dispatch table: ISA x aggregation variant -> function. The one place that
 * says which kernel runs a stage's aggregation; pgn_encode.c picks the variant from the
 * stage's plan (pgn_stage_plan.c) and takes its function from here (pgn_kernel_for).
 *
 * A build targets one ISA (what -march=native enables: AVX-512, else AVX2 + FMA, else
 * portable C), so only that ISA's row holds functions; the other rows name what they need.
 * Every entry gives the same results as the oracle (test_encoder_fast.py); a result
 * depends on its centre only, so the chunks of a cloud may run on either thread.
 */
#include "pgn_steps.h"

#if defined(__AVX512F__)
#define PGN_BUILD_ISA "avx512"
#elif defined(PGN_AVX2)
#define PGN_BUILD_ISA "avx2"
#else
#define PGN_BUILD_ISA "portable"
#endif

/* the job's centres [c0, c1): their indices and neighbour rows, count and K, offset rows */
#define ROWS(j, c0, c1) (j)->cidx + (c0), (j)->nb + (c0) * (j)->K, (c1) - (c0), (j)->K, \
    (j)->vx + (c0) * (j)->K * 3
#define OUT(j, c0) ((j)->out + (c0) * (j)->D2p)

/* portable C (compiled for the build's ISA: the compiler vectorises it as it can) */
static void direct(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    pgn_stage_aggregate(j->feat, j->D, ROWS(j, c0, c1), j->r, j->cc, j->ax, j->q,
                        OUT(j, c0), j->pe[tid], j->PS, j->mx[tid], j->sm[tid], NULL);
}

static void separable(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    pgn_stage_aggregate(j->feat, j->D, ROWS(j, c0, c1), j->r, j->cc, j->ax, j->q,
                        OUT(j, c0), j->pe[tid], j->PS, j->mx[tid], j->sm[tid],
                        (sep_t *)&j->fx[tid]);
}

#if defined(__AVX512F__)
#define AVX512_DIRECT direct
#if !defined(PGN_NO_NEIGHBOUR_LANES)
static void neighbour_lanes_avx512(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    pgn_aggregate_neighbour_lanes_avx512(j->feat, j->D, ROWS(j, c0, c1), j->r,
                                         j->lanes, j->ini, OUT(j, c0), j->lscr[tid]);
}
#define AVX512_NEIGHBOUR_LANES neighbour_lanes_avx512
#endif
#if !defined(PGN_NO_NARROW)
static void narrow_avx512(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    pgn_aggregate_narrow_avx512(j->feat, j->D, ROWS(j, c0, c1), j->r, j->ccs,
                                j->m1, j->m2, j->sc, OUT(j, c0), j->mx[tid]);
}
#define AVX512_NARROW narrow_avx512
#endif
#if defined(__AVX512VL__) && !defined(PGN_NO_SEPARABLE_AVX512)
static void separable_avx512(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    float *pe = j->pe[tid];
    const int64_t PS = j->PS;
    pgn_aggregate_separable_avx512(j->feat, j->D, ROWS(j, c0, c1), j->r, OUT(j, c0),
                                   j->mx[tid], j->sm[tid], pe, pe + PS, pe + 2 * PS,
                                   pe + 3 * PS, (sep_t *)&j->fx[tid]);
}
#define AVX512_SEPARABLE separable_avx512
#endif
#endif

#if defined(PGN_AVX2)
#define AVX2_DIRECT direct
#if !defined(PGN_NO_NEIGHBOUR_LANES)
static void neighbour_lanes_avx2(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    pgn_aggregate_neighbour_lanes_avx2(j->feat, j->D, ROWS(j, c0, c1), j->r,
                                       j->lanes, j->ini, OUT(j, c0), j->lscr[tid]);
}
#define AVX2_NEIGHBOUR_LANES neighbour_lanes_avx2
#endif
#if !defined(PGN_NO_NARROW)
static void narrow_avx2(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    pgn_aggregate_narrow_avx2(j->feat, j->D, ROWS(j, c0, c1), j->r, j->ccs,
                              j->lane_axis, j->sc, OUT(j, c0), j->mx[tid]);
}
#define AVX2_NARROW narrow_avx2
#if !defined(PGN_NO_NARROW_DERIVED)
static void narrow_derived_avx2(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    pgn_aggregate_narrow_derived_avx2(j->feat, j->D, ROWS(j, c0, c1), j->r,
                                      j->cents, j->sc, OUT(j, c0), j->mx[tid]);
}
#define AVX2_NARROW_DERIVED narrow_derived_avx2
#endif
#endif
#if !defined(PGN_NO_SEPARABLE_AVX2)
/* G, RV, G2, SRC in the pe buffers, which this kernel does not otherwise use */
static void separable_avx2(const agg_job *j, int tid, int64_t c0, int64_t c1) {
    float *pe = j->pe[tid];
    const int64_t PS = j->PS;
    pgn_aggregate_separable_avx2(j->feat, j->D, ROWS(j, c0, c1), j->r, OUT(j, c0),
                                 j->mx[tid], j->sm[tid], pe, pe + PS, pe + 3 * PS,
                                 (int32_t *)(pe + 2 * PS), pe + 4 * PS, pe + 5 * PS,
                                 (sep_t *)&j->fx[tid]);
}
#define AVX2_SEPARABLE separable_avx2
#endif
#endif

#ifndef AVX512_DIRECT
#define AVX512_DIRECT NULL
#endif
#ifndef AVX512_SEPARABLE
#define AVX512_SEPARABLE NULL
#endif
#ifndef AVX512_NARROW
#define AVX512_NARROW NULL
#endif
#ifndef AVX512_NEIGHBOUR_LANES
#define AVX512_NEIGHBOUR_LANES NULL
#endif
#ifndef AVX2_DIRECT
#define AVX2_DIRECT NULL
#endif
#ifndef AVX2_SEPARABLE
#define AVX2_SEPARABLE NULL
#endif
#ifndef AVX2_NARROW
#define AVX2_NARROW NULL
#endif
#ifndef AVX2_NARROW_DERIVED
#define AVX2_NARROW_DERIVED NULL
#endif
#ifndef AVX2_NEIGHBOUR_LANES
#define AVX2_NEIGHBOUR_LANES NULL
#endif

typedef struct {
    const char *isa;      /* the ISA row: avx512, avx2, portable */
    pgn_variant variant;
    const char *needs;    /* the CPU flags (/proc/cpuinfo) its code uses, space separated */
    pgn_aggregate_fn fn;  /* NULL: not built here (another ISA, or compiled out) */
} pgn_kernel;

static const char *const VARIANT_NAMES[PGN_NVARIANTS] = {
    "direct", "separable", "narrow", "narrow_derived", "neighbour_lanes"};

/* The table. Per ISA in the order the encoder prefers them for a stage that admits several;
 * portable last: it is every build's fallback for direct and separable. */
static const pgn_kernel TABLE[] = {
    {"avx512", PGN_NEIGHBOUR_LANES, "avx512f", AVX512_NEIGHBOUR_LANES},
    {"avx512", PGN_NARROW, "avx512f", AVX512_NARROW},
    {"avx512", PGN_SEPARABLE, "avx512f avx512vl", AVX512_SEPARABLE},
    {"avx512", PGN_DIRECT, "avx512f", AVX512_DIRECT},
    {"avx2", PGN_NEIGHBOUR_LANES, "avx2 fma", AVX2_NEIGHBOUR_LANES},
    {"avx2", PGN_NARROW_DERIVED, "avx2 fma", AVX2_NARROW_DERIVED},
    {"avx2", PGN_NARROW, "avx2 fma", AVX2_NARROW},
    {"avx2", PGN_SEPARABLE, "avx2 fma", AVX2_SEPARABLE},
    {"avx2", PGN_DIRECT, "avx2 fma", AVX2_DIRECT},
    {"portable", PGN_SEPARABLE, "", separable},
    {"portable", PGN_DIRECT, "", direct},
};
#define NTABLE ((int)(sizeof(TABLE) / sizeof(TABLE[0])))

pgn_aggregate_fn pgn_kernel_for(pgn_variant v) {
    pgn_aggregate_fn portable = NULL;
    for (int i = 0; i < NTABLE; ++i) {
        if (TABLE[i].variant != v || !TABLE[i].fn) continue;
        if (!strcmp(TABLE[i].isa, PGN_BUILD_ISA)) return TABLE[i].fn;
        if (!strcmp(TABLE[i].isa, "portable")) portable = TABLE[i].fn;
    }
    return portable;
}

/* The ISA this build targets: avx512, avx2 or portable. */
const char *pgn_build_isa(void) { return PGN_BUILD_ISA; }

int pgn_dispatch_size(void) { return NTABLE; }

/* Entry i of the table: its ISA, variant name and needed CPU flags. Returns 1 when this
 * build holds its function, 0 when not, -1 for an i out of range. */
int pgn_dispatch_entry(int i, const char **isa, const char **variant, const char **needs) {
    if (i < 0 || i >= NTABLE) return -1;
    *isa = TABLE[i].isa;
    *variant = VARIANT_NAMES[TABLE[i].variant];
    *needs = TABLE[i].needs;
    return TABLE[i].fn != NULL;
}

/* The name of variant v (pgn_stage_variants' codes), or NULL. */
const char *pgn_variant_name(int v) {
    return v >= 0 && v < PGN_NVARIANTS ? VARIANT_NAMES[v] : NULL;
}
