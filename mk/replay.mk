# Issue 8: CAN log replay, decode and play (hil/logio.py, hil/replay.py, hil/decode_log.py,
# hil/player.py; docs/replay.md).
.PHONY: replay-refs replay-logs replay-test replay-report

REPLAY_LOG_DIR := tests/data/logs
# The recorded test logs: every log with a sidecar <log>.json.
REPLAY_LOGS := $(patsubst %.json,%,$(wildcard $(REPLAY_LOG_DIR)/*.json))
REPLAY_RESULTS := results/replay

# Regenerate the reference outputs (<log name>.ref.log) of the test logs from the current
# ECU build, after an intended change of the ECU or a controller; review their git diff.
## regenerate the reference outputs of the test logs after an intended ECU change
replay-refs: setup
	@for log in $(REPLAY_LOGS); do \
		$(PY) -m hil replay $$log --write-ref --replace > /dev/null || exit 1; \
		echo "reference of $$log regenerated"; \
	done

# Re-record the test logs themselves (rarely: after a change of the contract or the HIL),
# then their references.
## re-record the test logs (after a contract or HIL change), then their references
replay-logs: setup
	$(PY) $(REPLAY_LOG_DIR)/make_logs.py
	$(MAKE) replay-refs

## tests of log reading, replay, decode and play
replay-test: setup
	$(PY) -m pytest -q tests/test_logio.py tests/test_replay.py tests/test_replay_logs.py \
		tests/test_replay_cli.py tests/test_decode_log.py tests/test_play.py

# The figures of docs/replay.md: replay reports of the test logs (a real-time recording
# compared within tolerances, as replay asks for it) and a decoded log (CSV + plot) in
# results/replay/. No wall time in them: a rerun of the same code writes the same bytes.
## replay reports and a decoded log of the test logs -> results/replay/
replay-report: setup
	@mkdir -p $(REPLAY_RESULTS)
	@for log in $(REPLAY_LOGS); do \
		name=$$(basename $$log); \
		mode=$$($(PY) -c 'import json, sys; print(json.load(open(sys.argv[1])).get("mode", ""))' $$log.json); \
		if [ "$$mode" = realtime ]; then compare="--compare tolerance"; else compare=; fi; \
		$(PY) -m hil replay $$log $$compare --replace --json $(REPLAY_RESULTS)/$$name.json \
			> $(REPLAY_RESULTS)/$$name.txt 2>&1; \
		echo "replay $$name: exit $$? -> $(REPLAY_RESULTS)/$$name.txt"; \
	done
	$(PY) -m hil decode $(REPLAY_LOG_DIR)/faults_lmpc.asc --replace --csv $(REPLAY_RESULTS)/faults_lmpc.csv \
		--plot $(REPLAY_RESULTS)/faults_lmpc.png | tee $(REPLAY_RESULTS)/faults_lmpc_decode.txt
	$(PROVENANCE_STAMP) $(foreach log,$(REPLAY_LOGS),$(REPLAY_RESULTS)/$(notdir $(log)).json $(REPLAY_RESULTS)/$(notdir $(log)).txt) \
		$(addprefix $(REPLAY_RESULTS)/faults_lmpc,.csv .png _decode.txt) --command "make replay-report" \
		--inputs $(REPLAY_LOGS) $(addsuffix .json,$(REPLAY_LOGS)) $(PROVENANCE_HIL) \
		--modules hil.commands.replay hil.commands.decode
