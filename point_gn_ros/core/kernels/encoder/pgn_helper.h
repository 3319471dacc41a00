/* A one-cloud batch's steps shared by the caller and the process's one helper thread
 * (pgn_helper.c). Each step is cut into chunks claimed from an atomic counter; a chunk's
 * result must depend on that chunk only, so that the split never changes a bit. */
#ifndef PGN_HELPER_H
#define PGN_HELPER_H

#include <stdint.h>

typedef void (*pgn_chunk_fn)(void *job, int tid, int64_t chunk);  /* tid: 0 caller, 1 helper */
typedef struct pgn_par pgn_par;

/* The helper for one cloud, or NULL: another caller has it, or no thread can start.
 * Every pgn_par_begin that returned a helper is followed by pgn_par_end. */
pgn_par *pgn_par_begin(void);
/* Run chunks [0, nchunks) of job: with the helper, or all on this thread when p is NULL. */
void pgn_par_run(pgn_par *p, pgn_chunk_fn fn, void *job, int64_t nchunks);
/* Release the helper (it sleeps until the next cloud). */
void pgn_par_end(pgn_par *p);

#endif
