# Extended state observer (models/eso.py, models/eso_dk.py) and the Fig. 7 robustness study.
.PHONY: fig7 test-eso

FIG7_RESULTS := $(addprefix results/fig7_,a_nominal.png b_low_mu.png c_mass.png rmse.md \
	gain_sweep.md drives.npz)

# DK vs ESO-DK along a 60 s drive under nominal, mu 0.55 and +200 kg conditions:
# results/fig7_<case>.png, results/fig7_rmse.md, results/fig7_gain_sweep.md.
# Needs the trained artefact models/artifacts/dk_d5.npz (make train); drives are cached in
# results/fig7_drives.npz (add FIG7_ARGS=--resimulate to rerun the plant).
## Fig. 7: DK vs ESO-DK prediction under nominal, low-mu and +200 kg -> results/fig7_*
fig7: setup
	$(PY) -m studies.fig7 $(FIG7_ARGS)
	$(PROVENANCE_STAMP) $(FIG7_RESULTS) --command "$(call provenance_command,fig7,FIG7_ARGS)" \
		--inputs $(PROVENANCE_VEHICLE) $(PROVENANCE_ARTEFACT) --modules studies.fig7

## tests of the extended state observer and the Fig. 7 study
test-eso: setup
	$(PY) -m pytest -q tests/test_eso.py tests/test_eso_dk.py tests/test_eso_fig7.py
