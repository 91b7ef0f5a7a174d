/*
 * Path files: the CSV reader and the contract's checks of controller/reference.py
 * (read_path_csv, check_path_file, ReferencePath.from_arrays), with the same messages, into
 * a pool of the ECU's paths by PATH_ID (all together at most ECU_MAX_PATH_POINTS points).
 * The pool is the caller's storage (static or zeroed: no heap); start-up fills it, the
 * control task reads it.
 */
#ifndef ECU_PATH_READER_H
#define ECU_PATH_READER_H

#include <stddef.h>

#include "ecu_types.h"

#define ECU_MAX_POOL_PATHS 256

/* One path as ReferencePath holds it: n points x, y (m), yaw (rad, unwrapped), s (m). */
typedef struct {
  const double *x, *y, *yaw, *s;
  int n;
} ecu_path_view_t;

typedef struct {
  /* Every loaded path, one after the other; the file being read goes to the free end. */
  double x[ECU_MAX_PATH_POINTS], y[ECU_MAX_PATH_POINTS], yaw[ECU_MAX_PATH_POINTS], s[ECU_MAX_PATH_POINTS];
  int lines[ECU_MAX_PATH_POINTS]; /* the file's line of each point (messages) */
  int used;
  struct { int id, first, n; } slices[ECU_MAX_POOL_PATHS];
  int n_slices;
} ecu_path_pool_t;

/* Forget every path. */
void ecu_paths_reset(ecu_path_pool_t *pool);

/* Read and check one more file as PATH_ID path_id; 0, or -1 with one line in err. */
int ecu_paths_add(ecu_path_pool_t *pool, int path_id, const char *file, char *err, size_t err_len);

/* Whether PATH_ID path_id is loaded. */
int ecu_paths_has(const ecu_path_pool_t *pool, int path_id);

/* The path PATH_ID (the last loaded with that ID); 0, or -1 when none (view untouched). */
int ecu_paths_find(const ecu_path_pool_t *pool, int path_id, ecu_path_view_t *view);

#endif
