/*
 * A minimal .npz writer (numpy's np.savez layout: a stored, uncompressed zip of .npy
 * files, format 1.0) for the ECU's timing record, so that firmware_sim.timing.load_timing
 * and the timing study read the C ECU's record as the Python ECU's. Off the control loop.
 */
#include <stdio.h>
#include <string.h>

#include "ecu_npz.h"

static uint32_t crc_table[256];

static void crc_init(void) {
  for (uint32_t n = 0; n < 256; n++) {
    uint32_t c = n;
    for (int k = 0; k < 8; k++) c = c & 1u ? 0xEDB88320u ^ (c >> 1) : c >> 1;
    crc_table[n] = c;
  }
}

static uint32_t crc_update(uint32_t crc, const uint8_t *data, size_t n) {
  crc = ~crc;
  for (size_t i = 0; i < n; i++) crc = crc_table[(crc ^ data[i]) & 0xFFu] ^ (crc >> 8);
  return ~crc;
}

static void put16(uint8_t *p, uint32_t v) {
  p[0] = (uint8_t)v;
  p[1] = (uint8_t)(v >> 8);
}

static void put32(uint8_t *p, uint32_t v) {
  put16(p, v);
  put16(p + 2, v >> 16);
}

/* The .npy header of one array: magic, version 1.0, the dict padded to a multiple of 64. */
static size_t npy_header(uint8_t *out, const char *descr, const char *shape) {
  char dict[200];
  int n = snprintf(dict, sizeof dict, "{'descr': '%s', 'fortran_order': False, 'shape': %s, }", descr, shape);
  size_t total = 10 + (size_t)n + 1;
  size_t padded = (total + 63) / 64 * 64;
  memcpy(out, "\x93NUMPY\x01\x00", 8);
  put16(out + 8, (uint32_t)(padded - 10));
  memcpy(out + 10, dict, (size_t)n);
  memset(out + 10 + n, ' ', padded - total);
  out[padded - 1] = '\n';
  return padded;
}

int npz_write(const char *path, const npz_array_t *arrays, int n_arrays, char *err, size_t err_len) {
  static uint8_t header[256];
  uint32_t offsets[16], crcs[16], sizes[16];
  uint8_t local[30], central[46], end[22];
  uint32_t offset = 0;
  if (n_arrays > 16) return -1;
  crc_init();
  FILE *file = fopen(path, "wb");
  if (!file) {
    snprintf(err, err_len, "%s: cannot write the timing record", path);
    return -1;
  }
  for (int i = 0; i < n_arrays; i++) {
    const npz_array_t *a = &arrays[i];
    char name[64];
    size_t name_len = (size_t)snprintf(name, sizeof name, "%s.npy", a->name);
    size_t head_len = npy_header(header, a->descr, a->shape);
    crcs[i] = crc_update(crc_update(0, header, head_len), a->data, a->bytes);
    sizes[i] = (uint32_t)(head_len + a->bytes);
    offsets[i] = offset;
    memset(local, 0, sizeof local);
    put32(local, 0x04034b50u);
    put16(local + 4, 20);
    put16(local + 12, 0x21); /* 1980-01-01 */
    put32(local + 14, crcs[i]);
    put32(local + 18, sizes[i]);
    put32(local + 22, sizes[i]);
    put16(local + 26, (uint32_t)name_len);
    fwrite(local, 1, sizeof local, file);
    fwrite(name, 1, name_len, file);
    fwrite(header, 1, head_len, file);
    fwrite(a->data, 1, a->bytes, file);
    offset += (uint32_t)(sizeof local + name_len) + sizes[i];
  }
  uint32_t directory_start = offset, directory_size = 0;
  for (int i = 0; i < n_arrays; i++) {
    char name[64];
    size_t name_len = (size_t)snprintf(name, sizeof name, "%s.npy", arrays[i].name);
    memset(central, 0, sizeof central);
    put32(central, 0x02014b50u);
    put16(central + 4, 20);
    put16(central + 6, 20);
    put16(central + 14, 0x21);
    put32(central + 16, crcs[i]);
    put32(central + 20, sizes[i]);
    put32(central + 24, sizes[i]);
    put16(central + 28, (uint32_t)name_len);
    put32(central + 42, offsets[i]);
    fwrite(central, 1, sizeof central, file);
    fwrite(name, 1, name_len, file);
    directory_size += (uint32_t)(sizeof central + name_len);
  }
  memset(end, 0, sizeof end);
  put32(end, 0x06054b50u);
  put16(end + 8, (uint32_t)n_arrays);
  put16(end + 10, (uint32_t)n_arrays);
  put32(end + 12, directory_size);
  put32(end + 16, directory_start);
  fwrite(end, 1, sizeof end, file);
  if (fclose(file) != 0) {
    snprintf(err, err_len, "%s: cannot write the timing record", path);
    return -1;
  }
  return 0;
}
