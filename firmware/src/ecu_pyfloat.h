/*
 * Python's float arithmetic in C (ecu_pyfloat.c), for results equal to the Python ECU's.
 */
#ifndef ECU_PYFLOAT_H
#define ECU_PYFLOAT_H

#include <stddef.h>

/* float.__floordiv__ as CPython computes it (float_floor_div). */
double py_floordiv(double vx, double wx);

/* float.__mod__ (the result takes the divisor's sign). */
double py_mod(double vx, double wx);

/* repr(float): the shortest form that reads back, ".0" added to an integral one. */
void py_repr(char *buf, size_t len, double v);

#endif
