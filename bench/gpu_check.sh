#!/usr/bin/env bash
# The device check, one call on the GPU machine (bench/gpu.py's docstring says what runs where):
#   here:  python bench/gpu.py prepare gpuw   (gpuw/ and .whl/ ignored through .git/info/exclude; .whl holds the
#          wheels the GPU image lacks: tyro, docstring_parser, typeguard, trimesh, kornia, kornia_rs for cp312)
#   there: bash bench/gpu_check.sh            (carry: gpuw, .whl; about 5 minutes) → $OUT: logs.tar (the CUDA
#          tests', the graph's and the profile's logs, gpu.json, graph.json) and the trained models of the cow and
#          DTU runs (tars; the quality cow's split in 15 MB parts, as a file comes back up to 16 MiB)
#   here:  cat the parts, unpack the tars into gpuw/, then python bench/gpu.py evaluate gpuw
set -u
export PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  && export PYTHONPATH=/tmp/site || exit 1
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"
mkdir -p logs
# the core ops on CUDA against CPU, the field interface on both, the surface finding's CUDA graphs
timeout 60 python3 -m pytest -q -p no:cacheprovider tests/dvr/test_device.py tests/dvr/test_fields.py tests/dvr/test_march.py \
  tests/dvr/test_surface_graph.py > logs/tests.log 2>&1
tail -3 logs/tests.log
# a step's surface finding eagerly, with fixed shapes, and as trained (one CUDA graph)
timeout 45 python3 bench/gpu.py graph gpuw > logs/graph.log 2>&1; tail -4 logs/graph.log
# where a default step's time goes: launches and waits for the device
timeout 45 python3 bench/gpu.py profile gpuw > logs/profile.log 2>&1; tail -2 logs/profile.log
# the trainings, the default cow also without the graphs (the baseline on the same machine), then the batch's four
# captures (fast preset: bench/batch.py --gpu-train takes their mean)
timeout 330 python3 bench/gpu.py train gpuw cow:default cow:default:eager cow:quality dtu:default torus_noise:fast \
  torus_fine:fast torus_thick:fast torus_high:fast 2>&1 | tee logs/train.log
cp gpuw/gpu.json gpuw/graph.json logs/ 2>/dev/null
tar cf $OUT/logs.tar logs
for r in cow_default cow_default_eager dtu_default cow_quality; do
  [ -f gpuw/runs/$r/.stages/train.json ] && tar cf $OUT/$r.tar -C gpuw/runs/$r model/final.pt model/config.json \
    .stages/train.json
done
[ -f $OUT/cow_quality.tar ] && split -b 15M $OUT/cow_quality.tar $OUT/cow_quality.tar. && rm $OUT/cow_quality.tar
ls -la $OUT
