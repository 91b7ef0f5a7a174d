/*
 * The OS layer on Linux: POSIX clocks and signals, SocketCAN raw sockets and the
 * socketcand TCP protocol. The only file with OS calls; the rest of the firmware is C11
 * with libc's stdio and libm.
 */
#define _GNU_SOURCE /* sched_setaffinity, ppoll */

#include <arpa/inet.h>
#include <errno.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "os.h"

int64_t os_monotonic_ns(void) {
  struct timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return (int64_t)now.tv_sec * 1000000000 + now.tv_nsec;
}

int os_sleep_until_ns(int64_t deadline_ns) {
  struct timespec deadline = {(time_t)(deadline_ns / 1000000000), (long)(deadline_ns % 1000000000)};
  int status = clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &deadline, NULL);
  return status == 0 ? 0 : -1;
}

static volatile sig_atomic_t *stop_flag;

static void on_stop_signal(int signum) {
  (void)signum;
  if (stop_flag) *stop_flag = 1;
}

void os_install_stop_handler(volatile sig_atomic_t *stop) {
  struct sigaction action;
  memset(&action, 0, sizeof action);
  action.sa_handler = on_stop_signal;
  sigemptyset(&action.sa_mask);
  stop_flag = stop;
  sigaction(SIGINT, &action, NULL);
  sigaction(SIGTERM, &action, NULL);
  sigaction(SIGHUP, &action, NULL);
}

int os_executable_folder(char *buf, size_t len) {
  ssize_t n = readlink("/proc/self/exe", buf, len - 1);
  if (n <= 0 || (size_t)n >= len - 1) return -1;
  buf[n] = '\0';
  char *slash = strrchr(buf, '/');
  if (!slash) return -1;
  *slash = '\0';
  return 0;
}

int os_realtime_policy(int cpu, int fifo_priority, char *note, size_t note_len, char *err, size_t err_len) {
  size_t used = 0;
  note[0] = '\0';
  if (cpu < -1) {
    snprintf(err, err_len, "--cpu must be >= 0, got %d", cpu);
    return -1;
  }
  if (fifo_priority) {
    int low = sched_get_priority_min(SCHED_FIFO), high = sched_get_priority_max(SCHED_FIFO);
    if (fifo_priority < low || fifo_priority > high) {
      snprintf(err, err_len, "SCHED_FIFO priority must be in %d..%d, got %d", low, high, fifo_priority);
      return -1;
    }
  }
  if (cpu >= 0) {
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(cpu, &set);
    if (sched_setaffinity(0, sizeof set, &set) != 0)
      used += (size_t)snprintf(note + used, note_len - used, "cpu %d not pinned: %s; ", cpu, strerror(errno));
  }
  if (fifo_priority) {
    struct sched_param param = {0};
    param.sched_priority = fifo_priority;
    if (sched_setscheduler(0, SCHED_FIFO, &param) != 0 && used < note_len)
      snprintf(note + used, note_len - used, "SCHED_FIFO not permitted: %s", strerror(errno));
  }
  return 0;
}

/* ------------------------------------------------------------------ CAN */
static int can_fd = -1;
static int can_socketcand; /* 1: socketcand's text protocol on a TCP stream */
static char stream_buffer[8192];
static size_t stream_used;

/* ppoll, not poll: poll's timeout is whole milliseconds, rounded up, so a wait for the
 * next release woke up to 1 ms late (release jitter p50 0.29 ms, p99 0.80 ms in make
 * timing); ppoll takes the remaining time to the nanosecond. */
static int wait_readable(int64_t timeout_ns) {
  struct pollfd pfd = {can_fd, POLLIN, 0};
  if (timeout_ns < 0) timeout_ns = 0;
  struct timespec timeout = {(time_t)(timeout_ns / 1000000000), (long)(timeout_ns % 1000000000)};
  int ready = ppoll(&pfd, 1, &timeout, NULL);
  if (ready < 0) return errno == EINTR ? 0 : OS_CAN_FAILED;
  return ready;
}

/* The next "< ... >" message of the socketcand stream into msg; 1, 0 (incomplete),
 * OS_CAN_ENDED or OS_CAN_FAILED. */
static int next_message(char *msg, size_t len, int64_t timeout_ns) {
  for (;;) {
    char *start = memchr(stream_buffer, '<', stream_used);
    char *end = start ? memchr(start, '>', stream_used - (size_t)(start - stream_buffer)) : NULL;
    if (start && end) {
      size_t n = (size_t)(end - start) + 1;
      snprintf(msg, len, "%.*s", (int)n, start);
      size_t consumed = (size_t)(end - stream_buffer) + 1;
      memmove(stream_buffer, stream_buffer + consumed, stream_used - consumed);
      stream_used -= consumed;
      return 1;
    }
    if (!start) stream_used = 0; /* nothing of a message: drop the noise */
    if (stream_used == sizeof stream_buffer) return OS_CAN_ENDED; /* not socketcand */
    int ready = wait_readable(timeout_ns);
    if (ready <= 0) return ready;
    ssize_t got = recv(can_fd, stream_buffer + stream_used, sizeof stream_buffer - stream_used, 0);
    if (got == 0) return OS_CAN_ENDED; /* the server closed the stream */
    if (got < 0) return errno == EINTR || errno == EAGAIN ? 0 : OS_CAN_FAILED;
    stream_used += (size_t)got;
    timeout_ns = 0;
  }
}

static int socketcand_command(const char *command, const char *expect, char *err, size_t err_len) {
  char reply[256];
  if (command && send(can_fd, command, strlen(command), MSG_NOSIGNAL) < 0) {
    snprintf(err, err_len, "socketcand: cannot send %s: %s", command, strerror(errno));
    return -1;
  }
  if (next_message(reply, sizeof reply, 5000000000LL) != 1 || strcmp(reply, expect) != 0) {
    snprintf(err, err_len, "socketcand: expected '%s' after '%s'", expect, command ? command : "connecting");
    return -1;
  }
  return 0;
}

int os_can_open(const char *interface, const char *channel, const char *host, int port, char *err,
                size_t err_len) {
  os_can_close();
  stream_used = 0;
  if (strcmp(interface, "socketcand") == 0) {
    struct sockaddr_in address;
    char command[128];
    int one = 1;
    memset(&address, 0, sizeof address);
    address.sin_family = AF_INET;
    address.sin_port = htons((uint16_t)port);
    if (inet_pton(AF_INET, host, &address.sin_addr) != 1) {
      snprintf(err, err_len, "socketcand: host %s is not an IPv4 address", host);
      return -1;
    }
    can_fd = socket(AF_INET, SOCK_STREAM, 0);
    if (can_fd < 0 || connect(can_fd, (struct sockaddr *)&address, sizeof address) != 0) {
      snprintf(err, err_len, "cannot open CAN bus (interface=socketcand, channel=%s): %s:%d: %s", channel, host,
               port, strerror(errno));
      os_can_close();
      return -1;
    }
    setsockopt(can_fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    can_socketcand = 1;
    snprintf(command, sizeof command, "< open %s >", channel);
    if (socketcand_command(NULL, "< hi >", err, err_len) || socketcand_command(command, "< ok >", err, err_len) ||
        socketcand_command("< rawmode >", "< ok >", err, err_len)) {
      os_can_close();
      return -1;
    }
    return 0;
  }
  if (strcmp(interface, "socketcan") == 0) {
    struct ifreq request;
    struct sockaddr_can address;
    can_fd = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (can_fd < 0) {
      snprintf(err, err_len, "cannot open CAN bus (interface=socketcan, channel=%s): %s", channel, strerror(errno));
      return -1;
    }
    memset(&request, 0, sizeof request);
    snprintf(request.ifr_name, sizeof request.ifr_name, "%s", channel);
    if (ioctl(can_fd, SIOCGIFINDEX, &request) != 0) {
      snprintf(err, err_len, "cannot open CAN bus (interface=socketcan, channel=%s): %s", channel, strerror(errno));
      os_can_close();
      return -1;
    }
    memset(&address, 0, sizeof address);
    address.can_family = AF_CAN;
    address.can_ifindex = request.ifr_ifindex;
    if (bind(can_fd, (struct sockaddr *)&address, sizeof address) != 0) {
      snprintf(err, err_len, "cannot open CAN bus (interface=socketcan, channel=%s): %s", channel, strerror(errno));
      os_can_close();
      return -1;
    }
    can_socketcand = 0;
    return 0;
  }
  snprintf(err, err_len, "interface %s: the C ECU has socketcan and socketcand", interface);
  return -1;
}

int os_can_send(uint32_t id, const uint8_t *data, int length) {
  if (can_fd < 0 || length < 0 || length > 8) return -1;
  if (can_socketcand) {
    char command[64];
    int used = snprintf(command, sizeof command, "< send %03X %X", (unsigned)id, (unsigned)length);
    for (int i = 0; i < length; i++) used += snprintf(command + used, sizeof command - (size_t)used, " %02X", data[i]);
    used += snprintf(command + used, sizeof command - (size_t)used, " >");
    return send(can_fd, command, (size_t)used, MSG_NOSIGNAL) == used ? 0 : -1;
  }
  struct can_frame frame;
  memset(&frame, 0, sizeof frame);
  frame.can_id = id & CAN_SFF_MASK;
  frame.can_dlc = (uint8_t)length;
  memcpy(frame.data, data, (size_t)length);
  return write(can_fd, &frame, sizeof frame) == (ssize_t)sizeof frame ? 0 : -1;
}

int os_can_recv(os_can_frame_t *out, int64_t timeout_ns) {
  if (can_fd < 0) return -1;
  if (can_socketcand) {
    char msg[256], id_text[16], hex[64];
    double seconds;
    for (;;) {
      int status = next_message(msg, sizeof msg, timeout_ns);
      if (status != 1) return status;
      timeout_ns = 0;
      hex[0] = '\0';
      if (sscanf(msg, "< frame %15s %lf %63[0-9a-fA-F] >", id_text, &seconds, hex) < 2) continue;
      size_t digits = strlen(id_text), n_hex = strlen(hex);
      if (n_hex % 2 || n_hex > 16) continue;
      out->id = (uint32_t)strtoul(id_text, NULL, 16);
      out->length = (int)(n_hex / 2);
      for (int i = 0; i < out->length; i++) {
        char byte[3] = {hex[2 * i], hex[2 * i + 1], '\0'};
        out->data[i] = (uint8_t)strtoul(byte, NULL, 16);
      }
      out->contract_kind = digits <= 3; /* 8 digits: an extended ID */
      return 1;
    }
  }
  int ready = wait_readable(timeout_ns);
  if (ready <= 0) return ready;
  struct can_frame frame;
  ssize_t got = read(can_fd, &frame, sizeof frame);
  if (got < 0) return errno == EINTR || errno == EAGAIN ? 0 : OS_CAN_FAILED;
  if (got != (ssize_t)sizeof frame) return OS_CAN_FAILED; /* CAN FD is not enabled here */
  out->contract_kind = !(frame.can_id & (CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG));
  out->id = frame.can_id & (frame.can_id & CAN_EFF_FLAG ? CAN_EFF_MASK : CAN_SFF_MASK);
  out->length = frame.can_dlc > 8 ? 8 : frame.can_dlc;
  memcpy(out->data, frame.data, (size_t)out->length);
  return 1;
}

void os_can_close(void) {
  if (can_fd >= 0) close(can_fd);
  can_fd = -1;
}
