# The ECU as C firmware (issue 18, docs/firmware.md): the control core libecu.so, built
# from firmware/src and the sources the generators write at build time (OSQP code
# generation of the three steering QPs, cantools' C frame codecs, the build's shapes, the
# inputs' hashes) plus the data file the C core reads at start-up (tuning + Koopman model
# + bicycle).
#   make firmware        - build/firmware/libecu.so, build/firmware/ecu_data.bin
#   make firmware-test   - the C core's tests (tests/test_firmware_c*.py; also in make test)
#   make firmware-equivalence - --native and the C executable vs the Python ECU, full lane changes
#   make firmware-conformance - the C and the Python ECU under 15 bus faults, frames compared
#                          (contract revisions 2 and 3: --release clock and sample)
#   make firmware-vcan   - the C ECU on vcan0 (user-mode Linux) vs the Python ECU, full lane change
#   make firmware-asan   - the same tests on an -fsanitize=address,undefined build (build/firmware-asan)
#   make firmware-cross  - the aarch64 cross build, replayed under qemu against the host build
#   make bench-native    - C step vs Python step on the same recorded inputs (JSON last line)
#   make firmware-footprint - text/data/bss of the executable, stack per function -> results/firmware_footprint.md
.PHONY: firmware-footprint firmware firmware-deps firmware-test firmware-equivalence firmware-conformance firmware-asan \
	firmware-cross firmware-vcan bench-native

FW_DIR := build/firmware
# The Koopman artefact (path without .npz/.json) the build's shapes and data file are for.
# Shapes are compile-time, so another model is another build: a test builds one with
# make firmware FW_DIR=build/firmware-bilinear FW_MODEL=build/firmware-bilinear/scheduled_bilinear
# (tests/test_firmware_c_bilinear.py); the default is the committed model.
FW_MODEL := models/artifacts/dk_d5
# The tuning file the QPs are generated for and the data file carries: another one (the
# actuator terms on, tests/test_firmware_c_actuator.py) is another build, as for FW_MODEL.
FW_TUNING := controller/tuning.toml
FW_GEN := $(FW_DIR)/gen
FW_CC ?= gcc
# -O3: the step 5-10 % faster than -O2 with the same results to the bit (no -ffast-math;
# ISO C mode keeps -ffp-contract=off, so no fused multiply-adds on FMA targets either).
FW_CFLAGS := -std=c11 -O3 -Wall -Wextra -Werror -fPIC -fvisibility=hidden
# Generated OSQP sources: the same flags, minus five warnings the generated code trips
# (unused static helpers and parameters, missing initialisers, an empty if body, && within ||).
FW_GEN_CFLAGS := $(FW_CFLAGS) -Wno-unused-function -Wno-missing-field-initializers \
	-Wno-empty-body -Wno-parentheses -Wno-unused-parameter
FW_SAN_FLAGS := -fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=all
# Python itself is not instrumented: the sanitizer runtimes are preloaded into it.
FW_SAN_PRELOAD = $(shell $(FW_CC) -print-file-name=libasan.so) $(shell $(FW_CC) -print-file-name=libubsan.so)
# Our sources see OSQP's public headers only; the generated OSQP sources also its private ones.
FW_INCLUDES := -Ifirmware/src -I$(FW_GEN) -I$(FW_GEN)/can -I$(FW_GEN)/qp -I$(FW_GEN)/qp/inc/public
FW_GEN_INCLUDES := $(FW_INCLUDES) -I$(FW_GEN)/qp/inc/private
# The library: every source but the executable's main.
FW_SOURCES := $(filter-out firmware/src/ecu_main.c,$(wildcard firmware/src/*.c))
# The executable: the library's sources but the default instances of the ctypes API
# (ecu_default.c; ecu_main.c has its own core and node), and its main.
FW_EXE_SOURCES := $(filter-out firmware/src/ecu_default.c,$(FW_SOURCES)) firmware/src/ecu_main.c
FW_HEADERS := $(wildcard firmware/src/*.h)
# The generators (firmware/tools/footprint.py only reports on the build).
FW_TOOLS := firmware/tools/ecu_data.py firmware/tools/generate.py
# Generator inputs: a change of any regenerates (their hashes are in ecu_version()).
FW_GEN_INPUTS := $(FW_TOOLS) $(FW_TUNING) controller/steering_qp.py models/vehicle.toml can_defs/vehicle.dbc \
	$(FW_MODEL).npz $(FW_MODEL).json
FW_PACKAGES := gcc cmake

## build the C control core build/firmware/libecu.so, the executable ecu and the data file
firmware: firmware-deps $(FW_DIR)/libecu.so $(FW_DIR)/ecu $(FW_DIR)/ecu_data.bin

# make test builds the firmware first (its tests load libecu.so); make bench times the C
# core's step beside the Python controllers and make timing runs the C ECU executable
# beside the Python ECU (the "NAME (C)" rows of studies/bench.py and studies/timing/).
# (through a variable, so make help keeps bench's and timing's own help lines)
FW_USERS := bench timing
test $(FW_USERS): firmware

## install gcc and cmake (as root, with apt-get) where they are missing
firmware-deps:
	@if command -v $(FW_CC) >/dev/null && command -v cmake >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing $(FW_PACKAGES)"; \
		DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(FW_PACKAGES) >/dev/null; \
	else echo "note: not root; the firmware needs: sudo apt-get install $(FW_PACKAGES)"; fi

# The model and tuning file this build is for, with their files' SHA-256. make compares
# dates only: without it, FW_MODEL=other (or FW_TUNING) into a build newer than the other
# model's files would keep the old model's sources and data. Rewritten only when its text
# changes, so the same choice rebuilds nothing (and the default build's check is cheap).
# (its recipe runs every time: the phony prerequisite is a path, so not a command of make help)
FW_CHOICE := $(FW_DIR)/model_choice
.PHONY: $(FW_CHOICE).check
$(FW_CHOICE): $(FW_CHOICE).check
	@mkdir -p $(@D)
	@{ echo "FW_MODEL $(FW_MODEL)"; echo "FW_TUNING $(FW_TUNING)"; \
		sha256sum $(FW_MODEL).npz $(FW_MODEL).json $(FW_TUNING); } > $@.new || { rm -f $@.new; exit 1; }
	@if cmp -s $@.new $@; then rm -f $@.new; else mv $@.new $@; fi

$(FW_GEN)/stamp: $(FW_GEN_INPUTS) $(FW_CHOICE) | $(STAMP)
	$(PY) firmware/tools/generate.py --out $(FW_GEN) --model $(FW_MODEL) --tuning $(FW_TUNING)
	touch $@

$(FW_DIR)/ecu_data.bin: $(FW_GEN_INPUTS) $(FW_CHOICE) | $(STAMP)
	$(PY) firmware/tools/ecu_data.py --out $@ --model $(FW_MODEL) --tuning $(FW_TUNING)

# One shared object from the core, the generated version source and the OSQP sources.
# (mk/firmware.mk too: a change of the compiler flags rebuilds)
$(FW_DIR)/libecu.so: $(FW_GEN)/stamp $(FW_SOURCES) $(FW_HEADERS) mk/firmware.mk
	@mkdir -p $(FW_DIR)/obj
	for f in $(FW_GEN)/qp/src/*.c $(FW_GEN)/qp/*_workspace.c; do \
		$(FW_CC) $(FW_GEN_CFLAGS) $(FW_EXTRA_CFLAGS) -fstack-usage $(FW_GEN_INCLUDES) -c $$f -o $(FW_DIR)/obj/$$(basename $$f .c).o || exit 1; \
	done
	$(FW_CC) $(FW_CFLAGS) $(FW_EXTRA_CFLAGS) $(FW_INCLUDES) -shared -o $@ $(FW_SOURCES) $(FW_GEN)/ecu_version.c \
		$(FW_GEN)/can/vehicle.c \
		$(FW_DIR)/obj/*.o -lm

# The executable: the same sources linked statically into one program (no libecu.so
# needed at run time); -fstack-usage writes each function's stack use (obj-ecu/*.su).
$(FW_DIR)/ecu: $(FW_DIR)/libecu.so firmware/src/ecu_main.c
	@mkdir -p $(FW_DIR)/obj-ecu
	rm -f $(FW_DIR)/obj-ecu/*.o $(FW_DIR)/obj-ecu/*.su
	cd $(FW_DIR)/obj-ecu && $(FW_CC) $(FW_CFLAGS) $(FW_EXTRA_CFLAGS) -fstack-usage $(addprefix -I$(CURDIR)/,$(subst -I,,$(FW_INCLUDES))) \
		-c $(addprefix $(CURDIR)/,$(FW_EXE_SOURCES) $(FW_GEN)/ecu_version.c $(FW_GEN)/can/vehicle.c)
	$(FW_CC) $(FW_CFLAGS) $(FW_EXTRA_CFLAGS) -o $@ $(FW_DIR)/obj-ecu/*.o $(FW_DIR)/obj/*.o -lm

## the C core's tests (libecu.so against the Python controllers)
firmware-test: firmware
	$(PY) -m pytest -q tests/test_firmware_c*.py

## --native and the C executable (on the socketcand hub) vs the Python ECU on both full lane changes
firmware-equivalence: firmware
	ECU_EQUIVALENCE_FULL=1 $(PY) -m pytest -q -s tests/test_firmware_c_equivalence.py tests/test_firmware_c_bus.py

## the C ECU and the Python ECU on the hub under 15 contract faults, clock and sample release (rev. 3): the same frames
firmware-conformance: firmware
	ECU_CONFORMANCE_FULL=1 $(PY) -m pytest -q -s tests/test_firmware_c_bus.py tests/test_conformance_rev3.py -k conformance

## the C ECU on a real vcan0 (host or user-mode Linux) vs the Python ECU, full lane change
firmware-vcan: firmware apt-deps
	ECU_VCAN_FULL=1 $(PY) -m pytest -q -s tests/test_firmware_c_vcan.py

## the C tests and fuzz (step, E2E, decode, executable) on a -fsanitize=address,undefined build
firmware-asan: firmware
	$(MAKE) --no-print-directory FW_DIR=build/firmware-asan FW_EXTRA_CFLAGS="$(FW_SAN_FLAGS)" \
		build/firmware-asan/libecu.so build/firmware-asan/ecu build/firmware-asan/ecu_data.bin
	ECU_LIB=build/firmware-asan/libecu.so ECU_EXE=build/firmware-asan/ecu LD_PRELOAD="$(FW_SAN_PRELOAD)" \
		ASAN_OPTIONS=detect_leaks=0 $(PY) -m pytest -q -p no:cacheprovider tests/test_firmware_c_core.py \
		tests/test_firmware_c_rx.py tests/test_firmware_c_exe.py tests/test_firmware_c_bus.py \
		tests/test_firmware_c_excite.py

## cross-compile for aarch64 Linux and check its replay under qemu equals the host build's
firmware-cross: firmware
	ECU_CROSS=1 $(PY) -m pytest -q -s tests/test_firmware_c_cross.py

## C control step vs the Python controller step on the same recorded inputs (last line JSON)
bench-native: firmware
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.bench_native

# The executable's sections (binutils size) and every function's own stack frame
# (-fstack-usage of our sources, cantools' codecs and the generated OSQP sources).
## text/data/bss of build/firmware/ecu and stack use per function -> results/firmware_footprint.md
firmware-footprint: firmware
	$(PY) firmware/tools/footprint.py --exe $(FW_DIR)/ecu --su $(FW_DIR)/obj-ecu --su $(FW_DIR)/obj \
		--out results/firmware_footprint.md
	$(PROVENANCE_STAMP) results/firmware_footprint.md --command "make firmware-footprint" \
		--inputs $(sort $(wildcard firmware/src/*.c firmware/src/*.h)) $(FW_GEN_INPUTS) firmware/tools/footprint.py mk/firmware.mk
