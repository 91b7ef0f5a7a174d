/*
 * The operating-system layer: everything the firmware needs from the OS, implemented in
 * one file per OS (os_linux.c). Porting to an RTOS or bare metal replaces that file only.
 */
#ifndef ECU_OS_H
#define ECU_OS_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>

/* Monotonic time in ns (never jumps with the wall clock). */
int64_t os_monotonic_ns(void);

/* Sleep until the monotonic time deadline_ns (absolute, so periods do not drift);
 * returns at once when it has passed. 0, or -1 when interrupted by a signal. */
int os_sleep_until_ns(int64_t deadline_ns);

/* SIGINT, SIGTERM and SIGHUP set *stop to 1 (the loops poll it). */
void os_install_stop_handler(volatile sig_atomic_t *stop);

/* Pin this process to cpu (-1: leave) and run it under SCHED_FIFO priority (0: leave).
 * A request the OS refuses is skipped with one line in note (empty when all was done);
 * -1 with err for a priority outside the OS's FIFO range or a negative cpu. */
int os_realtime_policy(int cpu, int fifo_priority, char *note, size_t note_len, char *err, size_t err_len);

/* The folder of this executable (no trailing slash) in buf; 0, or -1 when unknown. */
int os_executable_folder(char *buf, size_t len);

/* One CAN frame as the firmware sees it: ID, up to 8 bytes, and whether it is a classic
 * data frame with an 11-bit ID (the only kind the contract uses; others are ignored). */
typedef struct {
  uint32_t id;
  uint8_t data[8];
  int length;
  int contract_kind;
} os_can_frame_t;

/* Open the one bus: interface "socketcan" (a kernel CAN device such as vcan0 or can0,
 * raw socket) or "socketcand" (the daemon's TCP protocol on host:port, the transport of
 * the timing tests' hub). 0, or -1 with one line in err. */
int os_can_open(const char *interface, const char *channel, const char *host, int port, char *err,
                size_t err_len);

/* Send one classic frame; 0, or -1 when the bus refused it. */
int os_can_send(uint32_t id, const uint8_t *data, int length);

/* What os_can_recv returns besides 1 (frame filled) and 0 (none yet). */
#define OS_CAN_ENDED (-1)  /* the interface's stream ended: the bus is lost now */
#define OS_CAN_FAILED (-2) /* this receive failed; a lost bus once it persists (contract rev. 2) */

/* Wait up to timeout_ns for a frame: 1, 0, OS_CAN_ENDED or OS_CAN_FAILED. */
int os_can_recv(os_can_frame_t *frame, int64_t timeout_ns);

void os_can_close(void);

#endif
