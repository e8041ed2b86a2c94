#!/bin/bash
# the slow overload test with one busy core; extra env given as arguments
cd /work/main
python3 -c "while True: pass" &
HOG=$!
env "$@" OMP_NUM_THREADS=1 timeout 300 .venv/bin/pytest -q -s -p no:cacheprovider tests/daemon/test_daemon_overload.py::test_overload_real_pipeline 2>&1 | grep -E "overload:|passed|failed|^E  .*assert" | head -3
kill $HOG
