/* A minimal .npz writer (see ecu_npz.c). */
#ifndef ECU_NPZ_H
#define ECU_NPZ_H

#include <stddef.h>
#include <stdint.h>

/* One array: its name in the archive, numpy descr ("<f8", "<i8", "<U16"), shape text
 * ("(3, 6)", "(6,)", "()") and raw little-endian data. */
typedef struct {
  const char *name, *descr, *shape;
  const void *data;
  size_t bytes;
} npz_array_t;

/* Write the arrays to path; 0, or -1 with one line in err. */
int npz_write(const char *path, const npz_array_t *arrays, int n_arrays, char *err, size_t err_len);

#endif
