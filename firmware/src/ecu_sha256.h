/*
 * SHA-256 (FIPS 180-4) of a file, for the executable's --dbc check: the CAN matrix a user
 * names must be the one the codecs were generated from (its hash is in ecu_version()).
 */
#ifndef ECU_SHA256_H
#define ECU_SHA256_H

#include <stddef.h>

/* The file's SHA-256 as 64 lower-case hex digits and a NUL in hex (65 bytes), reading at
 * most about max_bytes. 0, -1 when the file cannot be read (errno set), -2 when it is
 * larger than max_bytes. */
int ecu_sha256_file(const char *path, char hex[65], long max_bytes);

#endif
