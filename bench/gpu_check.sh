#!/usr/bin/env bash
# The device check, one call on the GPU machine (bench/gpu.py's docstring says what runs where):
#   here:  python bench/gpu.py prepare gpuw   (gpuw/ and .whl/ ignored through .git/info/exclude; .whl holds the
#          wheels the GPU image lacks: tyro, docstring_parser, typeguard, trimesh, kornia, kornia_rs for cp312)
#   there: bash bench/gpu_check.sh [RUN...]   (carry: gpuw, .whl; about 4 minutes) → $OUT: logs.tar (the CUDA
#          tests', the graph's and the profile's logs, gpu.json, graph.json) and the trained models (a tar per run,
#          split in 15 MB parts where larger, as a file comes back up to 16 MiB)
#   here:  cat the parts, unpack each tar into gpuw/runs/RUN/, then python bench/gpu.py evaluate gpuw
set -u
export PYTHONUNBUFFERED=1
runs=("$@")
# bench/gpu.py's default runs: at most 8 files come back, the logs and a tar per run (the quality cow's in two parts)
[ ${#runs[@]} -gt 0 ] || runs=(cow:default cow:default:scale1 jar:default dtu:default dtu:default:scale1 cow:quality)
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
# where a default step's time goes, with the GPU's steps and the CPU's: launches and waits for the device
timeout 60 python3 bench/gpu.py profile gpuw > logs/profile.log 2>&1; grep -E "^gpu_batch_scale|^per step" logs/profile.log
# the trainings (RUN: SCENE:PRESET[:eager][:scaleN]; scale1 trains the CPU's steps on the GPU)
timeout 240 python3 bench/gpu.py train gpuw "${runs[@]}" 2>&1 | grep -v "it/s\]" | tee logs/train.log
cp gpuw/gpu.json gpuw/graph.json logs/ 2>/dev/null
tar cf $OUT/logs.tar logs
for d in gpuw/runs/*/; do
  r=$(basename $d)
  [ -f $d/.stages/train.json ] || continue
  tar cf $OUT/$r.tar -C $d model/final.pt model/config.json .stages/train.json
  [ $(stat -c %s $OUT/$r.tar) -gt 15000000 ] && split -b 15M $OUT/$r.tar $OUT/$r.tar. && rm $OUT/$r.tar
done
ls -la $OUT
