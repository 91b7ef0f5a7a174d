/*
 * build/firmware/ecu: the ECU executable.
 *
 *   ecu --version
 *   ecu --interface socketcan|socketcand --channel C [--host H --port P] --controller NAME
 *       --path ID=FILE.csv [--path ...] [--data FILE] (--lockstep | --realtime) [--cpu N]
 *       [--rt-priority P]     (pin to a CPU, SCHED_FIFO; skipped with a warning where refused)
 *       [--timing-out FILE.npz [--replace]]   (firmware_sim.timing's record, written on exit)
 *       [--model FILE.bin] [--dbc FILE.dbc] [--bitrate N] [--debug] [--log-level L]
 *       [--release clock|sample]  (what releases the control task: the 25 ms clock of
 *                            contract revision 2, the default, or revision 3's plant samples)
 *       [--plant-period 10|25]  (the plant's sample period; 25 ms only with --release sample)
 *       [--excite PROGRAM]  (identification excitation while ACTIVE: chirp, prbs, steps,
 *                            prbs-torque, or a .toml / .csv program file; ecu_excite.c)
 *   ecu --controller NAME --path ID=FILE.csv [--path ...] [--data FILE] [--path-id ID]
 *       --replay SAMPLES.csv [--realtime]
 *
 * On the bus (lockstep, or real time on absolute 25 ms deadlines; ecu_node.c) it is the
 * Python ECU's node: a model or path file that
 * does not load latches FAULT; SIGINT / SIGTERM / SIGHUP send one last STEER_TORQUE_CMD
 * with CMD_VALID = 0 and exit 0; a lost bus is reopened every second.
 * --replay steps the control core on recorded samples (CSV header
 * vx,vy,yaw_rate,x,y,yaw,steer_angle,drive_torque,target_speed) and writes one CSV row per
 * step to stdout; --realtime paces the steps on absolute 25 ms deadlines and counts
 * overruns on stderr. Bad arguments are one "error: ..." line on stderr and exit status 2
 * (1: the bus cannot be opened).
 *
 * Options of python -m firmware_sim, as far as they mean something here: --model takes a
 * data file (firmware/tools/ecu_data.py --model ARTEFACT --out FILE.bin writes it, and
 * --bicycle FITTED.json one with a fitted bicycle for lmpc; hil run --ecu c --model does
 * so itself), a Koopman artefact (.npz/.json) is refused with that command; --dbc must be the DBC the codecs were generated from (SHA-256 compared
 * with the build's); --bitrate is accepted and ignored with a note (SocketCAN sets the bit
 * rate on the interface, socketcand's daemon on its bus); --debug (or --log-level debug)
 * prints what was loaded at start-up. --log-level info (or debug) also prints the
 * scheduling obtained and, once the bus is open, one "ready: controller ..." line (as the
 * Python ECU: the timing study waits for it).
 */
#define _POSIX_C_SOURCE 200809L /* access, stat */

#include <ctype.h>
#include <errno.h>
#include <sys/stat.h>
#include <unistd.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ecu_node.h"
#include "ecu_sha256.h"
#include "os.h"

#define EXIT_USAGE 2
#define EXIT_BUS 1
#define RECV_TIMEOUT_NS 50000000LL /* bounds the reaction to a stop signal */
#define REOPEN_INTERVAL_NS 1000000000LL
#define BUS_LOST_AFTER_NS 100000000LL /* receive errors that persist this long: a lost bus */
#define RECV_RETRY_NS 10000000LL      /* the wait between failed receives */
#define MAX_PATHS 256
#define PERIOD_NS 25000000 /* Ts = 25 ms */
#define N_SAMPLE_FIELDS 9

/* The one core of the executable, its paths, its excitation and its node (static: no heap). */
static ecu_core_t core;
static ecu_path_pool_t paths;
static ecu_excite_t excitation;
static ecu_node_t node;
#define DBC_FILE_MAX 4194304L /* bytes of a --dbc file, as the Python ECU's */

static const char *const SAMPLE_HEADER = "vx,vy,yaw_rate,x,y,yaw,steer_angle,drive_torque,target_speed";
static const char *const USAGE =
  "usage: ecu --version\n"
  "       ecu --interface socketcan|socketcand --channel C [--host H] [--port P] --controller NAME\n"
  "           --path ID=FILE.csv [--path ID=FILE.csv ...] [--data FILE] (--lockstep | --realtime)\n"
  "           [--cpu N] [--rt-priority P] [--timing-out FILE.npz [--replace]] [--log-level L]\n"
  "           [--model FILE.bin] [--dbc FILE.dbc] [--bitrate N] [--debug] [--excite PROGRAM]\n"
  "           [--release clock|sample] [--plant-period 10|25]\n"
  "       ecu --controller NAME --path ID=FILE.csv [--path ID=FILE.csv ...] [--data FILE]\n"
  "           [--path-id ID] --replay SAMPLES.csv [--realtime]\n";

static volatile sig_atomic_t stop_requested;

static int fail(const char *message) {
  fprintf(stderr, "error: %s\n", message);
  return EXIT_USAGE;
}

/* "ID=FILE" -> id 0..255 and the file; 0 or -1. */
static int parse_path_argument(const char *text, int *id, const char **file) {
  char *end;
  const char *equals = strchr(text, '=');
  if (!equals || equals == text || equals[1] == '\0') return -1;
  long value = strtol(text, &end, 10);
  if (end != equals || value < 0 || value > 255) return -1;
  *id = (int)value;
  *file = equals + 1;
  return 0;
}

static int replay(FILE *samples, const char *name, int realtime) {
  static char line[4096];
  char message[600];
  int row = 1, overruns = 0;
  ecu_output_t out;
  if (!fgets(line, sizeof line, samples)) return fail("--replay: empty samples file");
  line[strcspn(line, "\r\n")] = '\0';
  if (strcmp(line, SAMPLE_HEADER) != 0) {
    snprintf(message, sizeof message, "--replay %s: line 1: header must be '%s'", name, SAMPLE_HEADER);
    return fail(message);
  }
  printf("steer_angle,drive_torque,status,iterations,fallback,observer_reset,step_time_us\n");
  int64_t deadline = os_monotonic_ns();
  while (!stop_requested && fgets(line, sizeof line, samples)) {
    double values[N_SAMPLE_FIELDS];
    char *cursor = line, *end;
    row++;
    for (int i = 0; i < N_SAMPLE_FIELDS; i++) {
      errno = 0;
      values[i] = strtod(cursor, &end);
      if (end == cursor || (i + 1 < N_SAMPLE_FIELDS ? *end != ',' : (*end != '\0' && *end != '\n' && *end != '\r'))) {
        snprintf(message, sizeof message, "--replay %s: line %d: expected %d numbers", name, row, N_SAMPLE_FIELDS);
        return fail(message);
      }
      cursor = end + 1;
    }
    if (realtime) {
      deadline += PERIOD_NS;
      if (os_monotonic_ns() > deadline) overruns++;
      os_sleep_until_ns(deadline);
    }
    ecu_sample_t sample = {values[0], values[1], values[2], values[3], values[4],
                           values[5], values[6], values[7], values[8]};
    ecu_core_step(&core, &sample, &out);
    printf("%.17g,%.17g,%d,%d,%d,%d,%.3f\n", out.steer_angle, out.drive_torque, out.status, out.iterations,
           out.fallback, out.observer_reset, out.step_time_s * 1e6);
  }
  if (realtime) fprintf(stderr, "replay: %d steps, %d overruns of the 25 ms deadline\n", row - 1, overruns);
  return 0;
}

/* Whether two names are one file: the same name, or the same device and inode (a link). */
static int same_file(const char *a, const char *b) {
  struct stat first, second;
  if (strcmp(a, b) == 0) return 1;
  return stat(a, &first) == 0 && stat(b, &second) == 0 && first.st_dev == second.st_dev &&
         first.st_ino == second.st_ino;
}

/* check_output_file of the Python CLI: refuse an output file that is one of the n_inputs
 * `inputs` (NULL entries skipped) or that the ECU could not write at its end, before
 * anything runs. NULL when fine, else the message. */
static const char *check_output_file(const char *file, int replace, const char *const *inputs, int n_inputs,
                                     char *message, size_t len) {
  struct stat info;
  char folder[512];
  for (int k = 0; k < n_inputs; k++) {
    if (inputs[k] && same_file(file, inputs[k])) {
      snprintf(message, len, "--timing-out %s: is one of the inputs of this run (%s)", file, inputs[k]);
      return message;
    }
  }
  const char *slash = strrchr(file, '/');
  snprintf(folder, sizeof folder, "%.*s", slash ? (int)(slash - file) : 1, slash ? file : ".");
  if (folder[0] == '\0') snprintf(folder, sizeof folder, "/");
  if (stat(folder, &info) != 0 || !S_ISDIR(info.st_mode)) {
    snprintf(message, len, "--timing-out %s: folder %s does not exist", file, folder);
    return message;
  }
  if (stat(file, &info) == 0) {
    if (S_ISDIR(info.st_mode)) snprintf(message, len, "--timing-out %s: is a folder", file);
    else if (!replace) snprintf(message, len, "--timing-out %s: file exists (give --replace to overwrite it)", file);
    else if (access(file, W_OK) != 0) snprintf(message, len, "--timing-out %s: file is not writable", file);
    else return NULL;
    return message;
  }
  if (access(folder, W_OK | X_OK) != 0) {
    snprintf(message, len, "--timing-out %s: folder %s is not writable", file, folder);
    return message;
  }
  return NULL;
}

/* --dbc: the file must be the DBC the codecs were generated from (its SHA-256 is the
 * ".dbc" line of ecu_version()). NULL when it is, else the message. */
static const char *check_dbc(const char *file, char *message, size_t len) {
  char given[65], built[65] = "", built_name[200] = "";
  int status = ecu_sha256_file(file, given, DBC_FILE_MAX);
  if (status == -2) { /* the Python ECU's message (can_defs/dbc.py DBC_FILE_MAX_BYTES) */
    snprintf(message, len, "cannot load DBC %s: larger than %ld bytes (the limit of this file)", file, DBC_FILE_MAX);
    return message;
  }
  if (status != 0) {
    snprintf(message, len, "--dbc %s: cannot read: %s", file, strerror(errno));
    return message;
  }
  for (const char *line = ecu_version(); *line;) {
    const char *end = strchr(line, '\n');
    size_t n = end ? (size_t)(end - line) : strlen(line);
    if (n > 70 && n < 64 + 2 + sizeof built_name && strncmp(line + n - 4, ".dbc", 4) == 0) {
      snprintf(built, sizeof built, "%.64s", line);
      snprintf(built_name, sizeof built_name, "%.*s", (int)(n - 66), line + 66);
    }
    line += end ? n + 1 : n;
  }
  if (strcmp(given, built) == 0) return NULL;
  snprintf(message, len, "--dbc %s: SHA-256 %s differs from the DBC this build's codecs were generated from "
           "(%s, SHA-256 %s); rebuild with make firmware for another CAN matrix", file, given, built_name, built);
  return message;
}

/* --model: the data file ecu_data.py writes; a Koopman artefact is refused with the
 * command that converts it. NULL when usable, else the message. */
static const char *check_model(const char *file, char *message, size_t len) {
  const char *dot = strrchr(file, '.');
  if (dot && (strcmp(dot, ".npz") == 0 || strcmp(dot, ".json") == 0)) {
    /* a .json is a Koopman artefact's metadata or a fitted bicycle (LMPC's) */
    snprintf(message, len, "--model %s: the C ECU reads the data file of a model, not its artefact: write it with "
             "'python firmware/tools/ecu_data.py %s %s --out FILE.bin'%s, then give --model FILE.bin "
             "(hil run --ecu c --model does this)", file, strcmp(dot, ".json") == 0 ? "--bicycle" : "--model", file,
             strcmp(dot, ".json") == 0 ? " (a fitted bicycle; --model for a Koopman artefact)" : "");
    return message;
  }
  return NULL;
}

static int send_on_bus(uint32_t id, const uint8_t *data, int length) { return os_can_send(id, data, length); }

/* The node on the bus until a stop signal; the bus is reopened every second while lost. */
static int run_bus(const char *interface, const char *channel, const char *host, int port, const char *load_error,
                   int realtime, int sample_release, int plant_period, const char *timing_out,
                   const char *ready) {
  char err[300];
  os_can_frame_t frame;
  if (os_can_open(interface, channel, host, port, err, sizeof err) != 0) {
    fprintf(stderr, "error: %s\n", err);
    return EXIT_BUS;
  }
  if (ready) {
    fprintf(stderr, "info: ready: %s\n", ready);
    fflush(stderr);
  }
  ecu_node_start(&node, &core, &paths, &excitation, send_on_bus, load_error);
  if (realtime) ecu_node_set_realtime(&node);
  if (sample_release) ecu_node_set_sample_release(&node);
  ecu_node_set_plant_period(&node, plant_period);
  os_install_stop_handler(&stop_requested);
  int lost = 0;
  int64_t next_reopen = 0, failing_since = -1;
  while (!stop_requested) {
    if (lost) {
      int64_t now = os_monotonic_ns();
      if (now >= next_reopen) {
        next_reopen = now + REOPEN_INTERVAL_NS;
        if (os_can_open(interface, channel, host, port, err, sizeof err) == 0) {
          fprintf(stderr, "warning: bus reopened after it was lost\n");
          lost = 0;
          continue;
        }
        fprintf(stderr, "error: bus still lost; reopening failed: %s\n", err);
      }
      /* Real time: the tasks keep running on their releases (the inputs time out:
       * DEGRADED, SAFE_STOP, STANDBY; nothing can be sent); lockstep: no tick, nothing. */
      int64_t wake = now + RECV_TIMEOUT_NS < next_reopen ? now + RECV_TIMEOUT_NS : next_reopen;
      if (realtime) {
        int64_t next = ecu_node_poll(&node, now);
        wake = next < wake ? next : wake;
      }
      os_sleep_until_ns(wake);
      continue;
    }
    int64_t wait = RECV_TIMEOUT_NS;
    if (realtime) {
      int64_t now = os_monotonic_ns(), next = ecu_node_poll(&node, now);
      if (next - now < wait) wait = next - now > 0 ? next - now : 0;
    }
    int status = os_can_recv(&frame, wait);
    if (status == 1) {
      ecu_node_frame(&node, frame.id, frame.data, frame.length, frame.contract_kind);
    }
    if (status >= 0) {
      failing_since = -1;
      continue;
    }
    /* Contract rev. 2: the end of the stream is a lost bus at once; receive errors only
     * once they persist for BUS_LOST_AFTER_NS (a single failed read is not a lost bus). */
    int64_t now = os_monotonic_ns();
    if (status == OS_CAN_FAILED) {
      if (failing_since < 0) {
        failing_since = now;
        fprintf(stderr, "warning: bus receive failed; the bus is lost if this persists for 100 ms\n");
      }
      if (now - failing_since < BUS_LOST_AFTER_NS) {
        os_sleep_until_ns(now + RECV_RETRY_NS); /* not a busy loop on a failing socket */
        continue;
      }
    }
    fprintf(stderr, "error: bus lost (%s); reopening it every second\n",
            status == OS_CAN_ENDED ? "end of the interface's stream" : "receive errors for 100 ms");
    os_can_close();
    lost = 1;
    failing_since = -1;
    next_reopen = now + REOPEN_INTERVAL_NS;
  }
  if (!lost) ecu_node_close(&node);
  os_can_close();
  if (timing_out && ecu_timing_save(&node.timing, timing_out, err, sizeof err) != 0) {
    fprintf(stderr, "error: --timing-out %s\n", err);
    return EXIT_BUS;
  }
  return 0;
}

int main(int argc, char **argv) {
  const char *controller = NULL, *data = "build/firmware/ecu_data.bin", *samples_file = NULL;
  const char *interface = NULL, *channel = NULL, *host = "127.0.0.1";
  const char *timing_out = NULL, *dbc = NULL, *model = NULL, *excite = NULL, *release = "clock";
  int debug = 0, info = 0, bitrate = 0;
  int port = 29536, lockstep = 0, cpu = -1, fifo_priority = 0, replace = 0, plant_period = 10;
  const char *path_files[MAX_PATHS];
  int path_ids[MAX_PATHS], n_paths = 0, selected = -1, realtime = 0, data_given = 0;
  char err[600], message[800];
  for (int i = 1; i < argc; i++) {
    const char *arg = argv[i], *value = i + 1 < argc ? argv[i + 1] : NULL;
    if (strcmp(arg, "--help") == 0 || strcmp(arg, "-h") == 0) {
      fputs(USAGE, stdout);
      printf("\nThe default data file is ecu_data.bin beside this executable. Bad arguments: one error line, "
             "exit 2; a bus that cannot be opened: exit 1. docs/firmware.md has the options.\n");
      return 0;
    } else if (strcmp(arg, "--version") == 0) {
      printf("ecu (ESO-DKMPC firmware), build shapes: %s\n%s", ecu_build_shapes(), ecu_version());
      return 0;
    } else if (strcmp(arg, "--realtime") == 0) {
      realtime = 1;
    } else if (strcmp(arg, "--lockstep") == 0) {
      lockstep = 1;
    } else if (strcmp(arg, "--replace") == 0) {
      replace = 1;
    } else if (strcmp(arg, "--debug") == 0) {
      debug = info = 1;
    } else if (!value && (strcmp(arg, "--controller") == 0 || strcmp(arg, "--path") == 0 ||
                          strcmp(arg, "--data") == 0 || strcmp(arg, "--replay") == 0 ||
                          strcmp(arg, "--path-id") == 0 || strcmp(arg, "--interface") == 0 ||
                          strcmp(arg, "--channel") == 0 || strcmp(arg, "--host") == 0 ||
                          strcmp(arg, "--port") == 0 || strcmp(arg, "--cpu") == 0 ||
                          strcmp(arg, "--rt-priority") == 0 || strcmp(arg, "--timing-out") == 0 ||
                          strcmp(arg, "--log-level") == 0 || strcmp(arg, "--dbc") == 0 ||
                          strcmp(arg, "--model") == 0 || strcmp(arg, "--bitrate") == 0 ||
                          strcmp(arg, "--excite") == 0 || strcmp(arg, "--release") == 0 ||
                          strcmp(arg, "--plant-period") == 0)) {
      snprintf(message, sizeof message, "%s needs a value", arg);
      fputs(USAGE, stderr);
      return fail(message);
    } else if (strcmp(arg, "--plant-period") == 0) {
      char *end;
      long value = strtol(argv[++i], &end, 10);
      if (*end != '\0' || end == argv[i]) {
        snprintf(message, sizeof message, "--plant-period: expected an integer, got '%s'", argv[i]);
        return fail(message);
      }
      if (value != 10 && value != 25) {
        snprintf(message, sizeof message, "--plant-period: plant_sample_period_ms must be 10 or 25, got %ld", value);
        return fail(message);
      }
      plant_period = (int)value;
    } else if (strcmp(arg, "--release") == 0) {
      release = argv[++i];
      if (strcmp(release, "clock") != 0 && strcmp(release, "sample") != 0) {
        snprintf(message, sizeof message, "--release: control_release must be one of clock, sample, got '%s'",
                 release);
        return fail(message);
      }
    } else if (strcmp(arg, "--controller") == 0) {
      controller = argv[++i];
    } else if (strcmp(arg, "--interface") == 0) {
      interface = argv[++i];
    } else if (strcmp(arg, "--channel") == 0) {
      channel = argv[++i];
    } else if (strcmp(arg, "--host") == 0) {
      host = argv[++i];
    } else if (strcmp(arg, "--port") == 0) {
      char *end;
      long value = strtol(argv[++i], &end, 10);
      if (*end != '\0' || value < 1 || value > 65535) return fail("--port: expected an integer in 1..65535");
      port = (int)value;
    } else if (strcmp(arg, "--cpu") == 0 || strcmp(arg, "--rt-priority") == 0) {
      char *end;
      long value = strtol(argv[++i], &end, 10);
      if (*end != '\0' || value < 0 || value > 4096) {
        snprintf(message, sizeof message, "%s: expected a non-negative integer, got '%s'", arg, argv[i]);
        return fail(message);
      }
      if (strcmp(arg, "--cpu") == 0) cpu = (int)value;
      else fifo_priority = (int)value;
    } else if (strcmp(arg, "--timing-out") == 0) {
      timing_out = argv[++i];
    } else if (strcmp(arg, "--log-level") == 0) {
      /* The C ECU writes its warnings and errors only; the levels are accepted for the
       * Python ECU's command lines. */
      const char *level = argv[++i];
      if (strcmp(level, "debug") && strcmp(level, "info") && strcmp(level, "warning") && strcmp(level, "error")) {
        snprintf(message, sizeof message, "--log-level: '%s' is not one of debug, info, warning, error", level);
        return fail(message);
      }
      if (strcmp(level, "debug") == 0) debug = 1;
      if (strcmp(level, "debug") == 0 || strcmp(level, "info") == 0) info = 1;
    } else if (strcmp(arg, "--dbc") == 0) {
      dbc = argv[++i];
    } else if (strcmp(arg, "--model") == 0) {
      model = argv[++i];
    } else if (strcmp(arg, "--excite") == 0) {
      excite = argv[++i];
    } else if (strcmp(arg, "--bitrate") == 0) {
      char *end;
      long value = strtol(argv[++i], &end, 10);
      if (*end != '\0' || value < 1 || value > 8000000) {
        snprintf(message, sizeof message, "--bitrate: expected a bit rate in 1..8000000 bit/s, got '%s'", argv[i]);
        return fail(message);
      }
      bitrate = (int)value;
    } else if (strcmp(arg, "--data") == 0) {
      data = argv[++i];
      data_given = 1;
    } else if (strcmp(arg, "--replay") == 0) {
      samples_file = argv[++i];
    } else if (strcmp(arg, "--path-id") == 0) {
      char *end;
      long id = strtol(argv[++i], &end, 10);
      if (*end != '\0' || id < 0 || id > 255) return fail("--path-id: expected an integer in 0..255");
      selected = (int)id;
    } else if (strcmp(arg, "--path") == 0) {
      int id;
      const char *file;
      if (parse_path_argument(argv[++i], &id, &file) != 0) {
        snprintf(message, sizeof message, "--path '%s': expected ID=FILE.csv with ID in 0..255", argv[i]);
        return fail(message);
      }
      for (int k = 0; k < n_paths; k++)
        if (path_ids[k] == id) {
          snprintf(message, sizeof message, "--path '%s': PATH_ID %d given twice (already %s)", argv[i], id,
                   path_files[k]);
          return fail(message);
        }
      if (n_paths < MAX_PATHS) {
        path_ids[n_paths] = id;
        path_files[n_paths++] = file;
      }
    } else {
      snprintf(message, sizeof message, "unknown argument %s", arg);
      fputs(USAGE, stderr);
      return fail(message);
    }
  }
  if (plant_period == 25 && strcmp(release, "sample") != 0) {
    snprintf(message, sizeof message, "--plant-period: plant_sample_period_ms 25 needs control_release 'sample', got '%s'",
             release);
    return fail(message);
  }
  if (!controller || n_paths == 0) {
    fputs(USAGE, stderr);
    return fail("--controller and at least one --path are required");
  }
  /* As the Python ECU: what cannot be used at all stops start-up before the bus opens. */
  static char controller_name[32];
  snprintf(controller_name, sizeof controller_name, "%s", controller);
  for (char *c = controller_name; *c; c++) *c = (char)tolower((unsigned char)*c);
  if (strcmp(controller_name, "eso-dkmpc") && strcmp(controller_name, "dkmpc") && strcmp(controller_name, "lmpc")) {
    snprintf(message, sizeof message, "--controller '%s': the C ECU has eso-dkmpc, dkmpc, lmpc", controller);
    return fail(message);
  }
  controller = controller_name;
  static char default_data[600];
  if (!data_given && !model) { /* the data file make firmware writes beside the executable */
    char folder[500];
    if (os_executable_folder(folder, sizeof folder) != 0) return fail("cannot find this executable's folder "
                                                                      "for its data file: give --data FILE");
    snprintf(default_data, sizeof default_data, "%s/ecu_data.bin", folder);
    data = default_data;
  }
  for (int k = 0; k < n_paths; k++) {
    struct stat info;
    if (stat(path_files[k], &info) == 0 && S_ISDIR(info.st_mode)) {
      snprintf(message, sizeof message, "--path '%d=%s': cannot read %s: it is a folder", path_ids[k], path_files[k],
               path_files[k]);
      return fail(message);
    }
  }
  if (model) {
    if (data_given) return fail("give --data or --model (a data file), not both");
    if (check_model(model, message, sizeof message)) return fail(message);
    data = model;
  }
  struct stat data_info;
  int data_is_folder = stat(data, &data_info) == 0 && S_ISDIR(data_info.st_mode);
  FILE *data_probe = data_is_folder ? NULL : fopen(data, "rb");
  if (!data_probe) {
    snprintf(message, sizeof message, "%s %s: cannot read the ECU data file: %s%s", model ? "--model" : "--data", data,
             data_is_folder ? "it is a folder" : strerror(errno), data_given || model ? "" : " (make firmware writes it)");
    return fail(message);
  }
  fclose(data_probe);
  if (dbc && check_dbc(dbc, message, sizeof message)) return fail(message);
  if (excite && !(interface || channel || lockstep))
    return fail("--excite runs on the bus (the excitation is added while ACTIVE), not with --replay");
  if (excite && ecu_excite_load(&excitation, excite, message, sizeof message) != 0) return fail(message);
  if (excite) fprintf(stderr, "warning: %s\n", ecu_excite_describe(&excitation));
  if (debug) {
    fprintf(stderr, "debug: controller %s, data file %s, build shapes: %s\n", controller, data, ecu_build_shapes());
    for (int k = 0; k < n_paths; k++) fprintf(stderr, "debug: PATH_ID %d: %s\n", path_ids[k], path_files[k]);
    if (dbc) fprintf(stderr, "debug: --dbc %s: the build's DBC (SHA-256 equal)\n", dbc);
  }
  if (interface || channel || lockstep) {
    static char load_error[700];
    if (!interface || !channel) return fail("--interface and --channel are required on the bus");
    if (samples_file) return fail("--replay runs without a bus: give no --interface / --channel");
    if (lockstep == realtime) return fail("exactly one of --lockstep or --realtime is required");
    /* the run's inputs (firmware_sim.inputs.command_inputs): no output overwrites one */
    const char *inputs[MAX_PATHS + 3];
    int n_inputs = 0;
    for (int k = 0; k < n_paths; k++) inputs[n_inputs++] = path_files[k];
    inputs[n_inputs++] = data;
    inputs[n_inputs++] = dbc;
    inputs[n_inputs++] = excite && ecu_excite_is_file(excite) ? excite : NULL;
    if (timing_out && check_output_file(timing_out, replace, inputs, n_inputs, message, sizeof message))
      return fail(message);
    if (bitrate)
      fprintf(stderr, "note: --bitrate %d ignored: %s\n", bitrate, strcmp(interface, "socketcand") == 0
              ? "socketcand's daemon sets its bus's bit rate"
              : "SocketCAN sets it on the interface (ip link set CHANNEL type can bitrate N; vcan has none)");
    for (int k = 0; k < n_paths; k++) {
      FILE *probe = fopen(path_files[k], "r");
      if (!probe) {
        snprintf(message, sizeof message, "--path '%d=%s': cannot read %s: %s", path_ids[k], path_files[k],
                 path_files[k], strerror(errno));
        return fail(message);
      }
      fclose(probe);
    }
    /* As the Python ECU: a model or path that does not load latches FAULT on the bus. */
    const char *failure = NULL;
    if (ecu_core_load(&core, data, controller, err, sizeof err) != 0) {
      snprintf(load_error, sizeof load_error, "controller '%s' failed to load: %s", controller, err);
      failure = load_error;
    }
    ecu_paths_reset(&paths);
    for (int k = 0; k < n_paths && !failure; k++) {
      if (ecu_paths_add(&paths, path_ids[k], path_files[k], err, sizeof err) != 0) {
        snprintf(load_error, sizeof load_error, "PATH_ID %d file %s: %s", path_ids[k], path_files[k], err);
        failure = load_error;
      }
    }
    if (failure) fprintf(stderr, "error: FAULT latched: %s\n", failure);
    else if (debug) fprintf(stderr, "debug: controller %s and %d path(s) loaded; opening %s %s\n", controller,
                            n_paths, interface, channel);
    if (cpu >= 0 || fifo_priority) {
      char note[300];
      if (os_realtime_policy(cpu, fifo_priority, note, sizeof note, err, sizeof err) != 0) return fail(err);
      if (note[0]) fprintf(stderr, "warning: %s\n", note);
      if (info)
        fprintf(stderr, "info: scheduling: cpu %d, %s%.0d%s%s%s\n", cpu, fifo_priority ? "SCHED_FIFO " : "SCHED_OTHER",
                fifo_priority, note[0] ? " (" : "", note, note[0] ? ")" : "");
    }
    static char ready[200];
    snprintf(ready, sizeof ready, "controller %s, %d path(s), %s, %s", controller, n_paths,
             realtime ? "real time" : "lockstep", failure ? "FAULT" : "loaded");
    return run_bus(interface, channel, host, port, failure, realtime, strcmp(release, "sample") == 0, plant_period, timing_out,
                   info ? ready : NULL);
  }
  if (ecu_core_load(&core, data, controller, err, sizeof err) != 0) return fail(err);
  /* Every path file is checked at start-up; the selected one is loaded last. */
  int chosen = 0;
  for (int k = 0; k < n_paths; k++)
    if (path_ids[k] == selected) chosen = k;
  if (selected >= 0 && path_ids[chosen] != selected) return fail("--path-id: no --path with that ID");
  ecu_paths_reset(&paths);
  for (int k = 0; k < n_paths; k++)
    if (ecu_paths_add(&paths, path_ids[k], path_files[k], err, sizeof err) != 0) return fail(err);
  if (ecu_core_select_path(&core, &paths, path_ids[chosen], err, sizeof err) != 0) return fail(err);
  if (!samples_file) return fail("give --interface / --channel / --lockstep (the bus) or --replay SAMPLES.csv");
  FILE *samples = fopen(samples_file, "r");
  if (!samples) {
    snprintf(message, sizeof message, "--replay %s: cannot read: %s", samples_file, strerror(errno));
    return fail(message);
  }
  os_install_stop_handler(&stop_requested);
  int status = replay(samples, samples_file, realtime);
  fclose(samples);
  return status;
}
