"""The fault campaign's run-and-verdict half (``make faults``, docs/faults.md): the cases
(`catalogue`; the input files' in `input_cases`), one case's run against the Python or the
C ECU on the HIL rig (`runs`, `python_ecu`, `c_ecu`, `relay`, `input_runs`) and its verdict
(`verdicts`). The campaign over every case, its executors and its report are
``studies.fault_campaign``, ``studies.fault_runs`` and ``studies.fault_report``.
"""
