#!/usr/bin/env bash
# The device check, one call on the GPU machine (bench/gpu.py's docstring says what runs where):
#   here:  python bench/gpu.py prepare gpuw   (gpuw/ and .whl/ ignored through .git/info/exclude; .whl holds the
#          wheels the GPU image lacks: tyro, docstring_parser, typeguard, trimesh, kornia, kornia_rs for cp312)
#   there: bash bench/gpu_check.sh            (carry: gpuw, .whl) → $OUT: gpu.json, the CUDA tests' log, the
#          trained models of the cow and DTU runs (tar), the profile
#   here:  unpack the tars into gpuw/, then python bench/gpu.py evaluate gpuw
set -u
export PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  && export PYTHONPATH=/tmp/site || exit 1
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"
# the core ops on CUDA against CPU, and the field interface on both
timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_device.py tests/test_fields.py 2>&1 | tee $OUT/tests.log \
  | tail -4
# a step's surface finding as trained, with fixed shapes, and as one CUDA graph (not yet measured on a GPU)
timeout 120 python3 bench/gpu.py graph gpuw 2>&1 | tail -4; cp gpuw/graph.json $OUT/ 2>/dev/null
timeout 330 python3 bench/gpu.py train gpuw cow:default dtu:default torus_noise:fast torus_fine:fast torus_thick:fast \
  torus_high:fast cow:quality
cp gpuw/gpu.json $OUT/ 2>/dev/null
for r in cow_default dtu_default cow_quality; do
  [ -f gpuw/runs/$r/.stages/train.json ] && tar cf $OUT/$r.tar -C gpuw/runs/$r model/final.pt model/config.json \
    .stages/train.json
done
timeout 60 python3 bench/gpu.py profile gpuw 2>&1 | tee $OUT/profile.log | tail -3
