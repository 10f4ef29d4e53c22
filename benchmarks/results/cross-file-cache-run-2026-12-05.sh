#!/bin/bash
# cross-file cache reuse in one cold process: default vs bound (EQX_ON_ERROR=nan, min compile time 0)
cd /work/main
FILES="tests/test_static.py tests/test_scenarios.py tests/test_config.py tests/test_fit.py tests/test_cli.py tests/test_geometry.py"
for mode in default bound; do
  d=/work/runs/xfile/cache-$mode; rm -rf $d
  if [ $mode = bound ]; then export EQX_ON_ERROR=nan XFILE_MIN0=1; fi
  echo "== $mode $(date)"
  PYTHONPATH=/work/runs/xfile:/work/main DIFFTISSUE_TEST_JAX_CACHE=$d MPLBACKEND=Agg CI=true /usr/bin/time -f "TIME user=%U sys=%S wall=%e rss=%M" \
    .venv/bin/python -m pytest -q -p no:cacheprovider -p xfile_plugin $FILES 2>&1 | grep -E "XFILE|TIME|passed|failed" 
done
