/* Bounded line reading (ecu_lines.h); a port of models/input_files.py's bounded_lines. */
#include <string.h>

#include "ecu_lines.h"

/* 1 when bytes[0..n) are UTF-8 as Python's strict decoder takes it: no overlong form, no
 * surrogate (U+D800..U+DFFF), nothing above U+10FFFF, no sequence cut short. */
static int utf8_valid(const unsigned char *bytes, size_t n) {
  size_t i = 0;
  while (i < n) {
    unsigned char lead = bytes[i];
    unsigned char low = 0x80, high = 0xBF; /* the range of the first continuation byte */
    size_t more;
    if (lead < 0x80) {
      i++;
      continue;
    }
    if (lead >= 0xC2 && lead <= 0xDF) {
      more = 1;
    } else if (lead >= 0xE0 && lead <= 0xEF) {
      more = 2;
      if (lead == 0xE0) low = 0xA0;  /* else overlong */
      if (lead == 0xED) high = 0x9F; /* else a surrogate */
    } else if (lead >= 0xF0 && lead <= 0xF4) {
      more = 3;
      if (lead == 0xF0) low = 0x90;  /* else overlong */
      if (lead == 0xF4) high = 0x8F; /* else above U+10FFFF */
    } else {
      return 0;
    }
    if (n - i - 1 < more) return 0;
    for (size_t k = 1; k <= more; k++) {
      unsigned char next = bytes[i + k];
      if (next < (k == 1 ? low : 0x80) || next > (k == 1 ? high : 0xBF)) return 0;
    }
    i += more + 1;
  }
  return 1;
}

int ecu_read_line(ecu_lines_t *lines, char *buf, char *err, size_t err_len) {
  size_t n = 0;
  int c = 0;
  while (n < ECU_LINE_MAX + 1 && (c = getc(lines->stream)) != EOF) {
    buf[n++] = (char)c;
    if (c == '\n') break;
  }
  if (n == 0) return 0;
  lines->number++;
  lines->total_bytes += (long)n;
  if (memchr(buf, '\0', n)) {
    snprintf(err, err_len, "%s: line %d: holds a NUL byte", lines->name, lines->number);
    return -1;
  }
  if (n > ECU_LINE_MAX) {
    snprintf(err, err_len, "%s: line %d: longer than %d bytes", lines->name, lines->number, ECU_LINE_MAX);
    return -1;
  }
  if (lines->total_bytes > lines->max_bytes) {
    snprintf(err, err_len, "%s: larger than %ld bytes (the limit of this file)", lines->name, lines->max_bytes);
    return -1;
  }
  if (!utf8_valid((const unsigned char *)buf, n)) { /* "\n" never falls inside a sequence */
    snprintf(err, err_len, "%s: line %d: not UTF-8", lines->name, lines->number);
    return -1;
  }
  if (buf[n - 1] == '\n') n--; /* the line's end: "\n" or "\r\n" */
  if (n > 0 && buf[n - 1] == '\r') n--;
  buf[n] = '\0';
  return 1;
}
