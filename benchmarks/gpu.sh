#!/usr/bin/env bash
# Runs on the lent GPU machine (see docs/benchmarks.md for how the figures were made).
# The machine has torch/lightning/scipy but not taichi, warp, hydra, trimesh, zarr (zarr 3.4 needs msgspec): they travel as
# wheels under .whl/ (warp split in three parts, one per call, imageio-ffmpeg in two; hydra-joblib-launcher in .whl/b
# for multiruns), made
# here by benchmarks/fetch_wheels.sh.
# Usage: bash benchmarks/gpu.sh <phase>
set -uo pipefail
phase=${1:-wheels}
# Carrying a run between machines (a lent machine goes back after 30 min; what comes back from a call is at most
# 64 MiB in files of 16 MiB, and what travels to one is at most 64 MiB): `pack` tars the outputs root (ROOT) into
# PART_MB pieces with their checksums; `fetch` leaves COUNT pieces from FROM in $OUT; on the next machine `unpack`
# gathers the pieces carried so far (under CARRY, e.g. .carry/) and, once every checksum matches, untars them.
# PACK_PATHS: only these paths under ROOT (shell globs, e.g. "dataset/demos-*"), default all of it.
case "$phase" in
  pack|fetch|unpack)
    ROOT=${ROOT:-/tmp/o}; P=${PACK_DIR:-/tmp/pack}; OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
    case "$phase" in
      pack)
        rm -rf "$P" && mkdir -p "$P"
        # shellcheck disable=SC2086 # PACK_PATHS is a list of globs, expanded inside ROOT
        # A live run's tree (a `bg` run still writing) changes while tar reads it: tar's status 1. Its open parts
        # still resume (an episode logged but not committed runs again), so that is a warning, not a failure.
        (cd "$ROOT" && tar -czf - ${PACK_PATHS:-.}) | split -b "${PART_MB:-15}M" -d -a 3 - "$P/o.tgz."
        st=("${PIPESTATUS[@]}")
        if [ "${st[0]}" = 1 ]; then echo "pack: $ROOT changed while packing (a live run); its open parts resume"
        elif [ "${st[0]}" != 0 ] || [ "${st[1]}" != 0 ]; then exit 1; fi
        (cd "$P" && sha256sum o.tgz.* > SHA256SUMS) && cp "$P/SHA256SUMS" "$OUT/"
        echo "packed $ROOT: $(ls "$P"/o.tgz.* | wc -l) pieces of ${PART_MB:-15} MiB at most, $(du -sh "$P" | cut -f1)" ;;
      fetch)
        cp "$P/SHA256SUMS" "$OUT/"
        ls "$P"/o.tgz.* | tail -n +$(( ${FROM:-0} + 1 )) | head -n "${COUNT:-3}" | xargs -r cp -t "$OUT/"
        echo "fetched: $(cd "$OUT" && ls o.tgz.* 2>/dev/null | tr '\n' ' ')" ;;
      unpack)
        mkdir -p "$P"
        for f in ${CARRY:-.carry}/*/o.tgz.* ${CARRY:-.carry}/*/SHA256SUMS; do [ -f "$f" ] && { [ -f "$P/${f##*/}" ] || cp "$f" "$P/"; }; done
        [ -f "$P/SHA256SUMS" ] || { echo "unpack: no SHA256SUMS carried under ${CARRY:-.carry}/" >&2; exit 2; }
        missing=$(cd "$P" && awk '{print $2}' SHA256SUMS | while read -r f; do [ -f "$f" ] || echo "$f"; done)
        if [ -n "$missing" ]; then echo "unpack: still missing $(echo $missing)"; exit 3; fi
        (cd "$P" && sha256sum --quiet -c SHA256SUMS) || { echo "unpack: a piece does not match its checksum" >&2; exit 2; }
        mkdir -p "$ROOT" && cat "$P"/o.tgz.* | tar -xzf - -C "$ROOT" && echo "unpacked into $ROOT" ;;
    esac
    exit $? ;;
esac
W=/tmp/w
mkdir -p "$W" /tmp/site
for f in .whl/*/*; do [ -f "$f" ] && cp --update=none "$f" "$W/"; done
if ls "$W"/warp.part0{0,1,2} >/dev/null 2>&1 && [ ! -f "$W/warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl" ]; then
  cat "$W"/warp.part00 "$W"/warp.part01 "$W"/warp.part02 > "$W/warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl"
fi
if ls "$W"/ffmpeg.part0{0,1} >/dev/null 2>&1 && [ ! -f "$W/imageio_ffmpeg-0.8.1-py3-none-manylinux_2_28_x86_64.whl" ]; then
  cat "$W"/ffmpeg.part00 "$W"/ffmpeg.part01 > "$W/imageio_ffmpeg-0.8.1-py3-none-manylinux_2_28_x86_64.whl"
fi
for whl in "$W"/*.whl; do
  [ -f "$whl" ] || continue  # no wheels carried (the torch-only recipes: reward, train)
  stamp="$W/.done-$(basename "$whl")"
  [ -f "$stamp" ] && continue
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$whl" && touch "$stamp"
done
# Run from a committed snapshot when one travels (.gpu/head.tar from `git archive HEAD`), so that
# uncommitted edits in the working tree cannot leak into measured code.
if [ -f .gpu/head.tar ]; then
  rm -rf /tmp/head && mkdir -p /tmp/head && tar -xf .gpu/head.tar -C /tmp/head && cd /tmp/head
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 WANDB_MODE=disabled
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
mps_start() {  # CUDA Multi-Process Service: one daemon, the GPU's settings untouched (compute mode stays Default)
  export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps-pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps-log
  mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY"
  nvidia-cuda-mps-control -d && echo "MPS daemon started" || echo "MPS: nvidia-cuda-mps-control failed"
}
mps_stop() { echo quit | nvidia-cuda-mps-control; sleep 1; echo "MPS daemon stopped"; }
case "$phase" in
  wheels) ls /tmp/site | head -50 ;;
  bench-sim)
    python3 benchmarks/sim_throughput.py --device cuda 2>&1 | tee "$OUT/bench_sim.txt" ;;
  warp-check)  # the warp scatter's CUDA check (the GPU part of tests/test_sim_warp_scatter.py)
    timeout 500 python3 - <<'PY' 2>&1 | grep -v -i warn | tee "$OUT/warp_check.txt"
import re
src = open("tests/test_sim_warp_scatter.py").read()
exec(re.search(r'GPU_CHECK = r"""(.*?)"""', src, re.S).group(1))
PY
    ;;
  warp-bench)  # the 84^3 batching gain, SVD and polar rotation (cold caches: ~40 s of compiling per case)
    for extra in "--rotation svd" "--rotation polar"; do
      echo "== $extra" | tee -a "$OUT/warp_bench.txt"
      timeout 240 python3 benchmarks/sim_throughput.py --device cuda --grids 84 --batches 1 16 $extra 2>&1 \
        | tail -3 | tee -a "$OUT/warp_bench.txt"
    done ;;
  bench-topo)  # every size, cut beside it (cold Warp/Taichi caches need the long timeout)
    timeout 500 python3 benchmarks/topology.py --device cuda 2>&1 | tee "$OUT/bench_topology.txt" ;;
  bench-mppi)
    timeout 400 python3 benchmarks/mppi.py --device cuda --K 16 --n-grid 64 2>&1 | tee "$OUT/bench_mppi.txt"
    timeout 300 python3 benchmarks/mppi.py --device cuda --K 16 --n-grid 64 --reward-backend torch 2>&1 \
      | tee -a "$OUT/bench_mppi.txt" ;;
  ncu-sim)  # Nsight Compute on a batched cut's scatter and gather (84^3, B=16, after 400 launches). With the grid
    # box on, p2g's tasks are: bounds, clear, box reset, scatter (kernel_3); g2p has one (kernel_0).
    timeout 400 ncu -k "regex:p2g.*kernel_3|g2p.*kernel_0" --launch-skip 400 --launch-count 2 \
      --section SpeedOfLight --section Occupancy --section LaunchStats --section WarpStateStats \
      --section MemoryWorkloadAnalysis --section ComputeWorkloadAnalysis python3 - <<'PY' 2>&1 | tee "$OUT/ncu_sim.txt"
from topocut.sim import CuttingEnv, KnifeAction, SimConfig
env = CuttingEnv(SimConfig(n_grid=84, batch_size=16, arch="cuda", dwell_time=0.0))
env.reset("cube")
env.cut([KnifeAction(0.5 + 0.02 * b / 15, 0.5, yaw=0.1 * b) for b in range(16)])
PY
    ;;
  block-dim)  # scatter / gather threads per block (Taichi's launch bounds cap registers at 65536 / (2 block_dim)),
    # every case timed in one process (the defaults: 289 s on an H100 with a cold cache, ~45 s of compiling a case)
    cases=${CASES:-"tuning.scatter_block_dim=128 tuning.scatter_block_dim=384 tuning.scatter_block_dim=448"}
    timeout 560 python3 benchmarks/sim_throughput.py --device cuda --grids ${GRIDS:-84 128} --batches ${BATCHES:-16} \
      --no-ref --repeats 5 --set $cases 2>&1 | tee -a "$OUT/block_dim.txt" ;;
  episodes)  # the episode engine: a demonstration cut vs its simulation, batched evaluation, PDDP act (#31)
    timeout ${LIMIT:-560} python3 benchmarks/episodes.py --device cuda --n-grid 64 --K 16 --iters 2 \
      --batch ${BATCH:-16} --eval-episodes ${EPISODES:-32} --only ${PARTS:-demo eval policy} ${BENCH_ARGS:-} 2>&1 \
      | grep -v -i warn | tee -a "$OUT/bench_episodes.txt" ;;
  reward)  # the reward's eigensolvers batched on the GPU: whole-spectrum eigh (reference), subspace, host (#31)
    timeout 300 python3 benchmarks/reward.py --device cuda 2>&1 | tee -a "$OUT/bench_reward.txt" ;;
  demo-procs)  # MPPI demonstrations from JOBS processes sharing the GPU (joblib launcher) vs one process (#31);
    # MPS=1: under CUDA's Multi-Process Service (its daemon started here, stopped after), processes' kernels overlap
    if [ "${MPS:-0}" = 1 ]; then mps_start; fi
    echo "== JOBS=${JOBS:-4} EPISODES=${EPISODES:-4} MPS=${MPS:-0} ${DEMO_ARGS:-}" | tee -a "$OUT/demo_procs.txt"
    timeout ${LIMIT:-560} python3 benchmarks/demo_processes.py --device cuda --jobs ${JOBS:-4} \
      --episodes ${EPISODES:-4} ${DEMO_ARGS:-} 2>&1 | grep -v -i warn | tee -a "$OUT/demo_procs.txt"
    if [ "${MPS:-0}" = 1 ]; then mps_stop; fi ;;
  train-sweep)  # perception training samples/s over batch sizes, fp32 and bf16 (#31)
    timeout ${LIMIT:-400} python3 benchmarks/train.py --device cuda --batches 16 64 256 512 --amp --steps 10 2>&1 \
      | grep -v -i warn | tee "$OUT/bench_train.txt" ;;
  protocol)  # the 405-episode protocol through stage=eval (resumes: run it again); POLICIES (default: the scripted
    # ones), EVAL_JOBS processes (MPS=1: under CUDA's Multi-Process Service), EVAL_ARGS more overrides
    if [ "${MPS:-0}" = 1 ]; then mps_start; fi
    echo "== POLICIES=${POLICIES:-oracle,heuristic} EVAL_JOBS=${EVAL_JOBS:-1} MPS=${MPS:-0} ${EVAL_ARGS:-}" \
      | tee -a "$OUT/protocol.txt"
    t0=$(date +%s)
    timeout ${LIMIT:-560} python3 -m topocut.run stage=eval scale=paper device=cuda sim.n_grid=${GRID:-64} \
      reward=torch "eval.policies=[${POLICIES:-oracle,heuristic}]" eval.train_seeds=1 eval.jobs=${EVAL_JOBS:-1} \
      eval.gifs=0 eval.videos=0 logger=none progress=false outputs_root=/tmp/o ${EVAL_ARGS:-} 2>&1 | grep -v -i warn | tail -40 \
      | tee -a "$OUT/protocol.txt"
    echo "wall $(( $(date +%s) - t0 )) s; episodes written: $(find /tmp/o/eval -name '*.json' -path '*episodes*' | wc -l)" \
      | tee -a "$OUT/protocol.txt"
    if [ "${MPS:-0}" = 1 ]; then mps_stop; fi
    find /tmp/o -name results.md -exec cp {} "$OUT/" \;
    tar -czf "$OUT/protocol_eval.tgz" -C /tmp/o eval 2>/dev/null ;;
  oracle-check)  # the answer key (#47): the oracle through stage=eval at scale=paper (128^3, 3 cm pieces) and at 64^3
    # with 5 cm pieces, EPC episodes a cell (default 5: 135 episodes each), EVAL_JOBS processes under MPS;
    # experiments/oracle_audit.py --summary tabulates R per task x split and object, success, and the worst IoU of a
    # discovered piece with the simulator's own piece; EVAL_ARGS: more overrides (e.g. topology.min_piece_particles=8)
    mps_start
    for grid in ${GRIDS:-128 64}; do
      name=${NAME:-oracle}$grid  # NAME: another run's name, beside the default one (e.g. a setting compared)
      extra="eval.name=$name"
      [ "$grid" = 64 ] && extra="$extra eval.task_overrides={slice:{thickness:0.05},stick:{thickness:0.05,width:0.05},dice:{size:0.05}}"
      t0=$(date +%s)
      timeout ${LIMIT:-560} python3 -m topocut.run stage=eval scale=paper device=cuda reward=torch sim.n_grid=$grid \
        sim.batch_size=4 "eval.policies=[oracle]" eval.train_seeds=1 eval.jobs=${EVAL_JOBS:-12} eval.gifs=0 eval.videos=0 \
        eval.episodes_per_cell=${EPC:-5} logger=none progress=false outputs_root=/tmp/o $extra ${EVAL_ARGS:-} 2>&1 \
        | grep -v -i warn | tail -5 | tee -a "$OUT/oracle_check.txt"
      echo "== ${grid}^3: wall $(( $(date +%s) - t0 )) s" | tee -a "$OUT/oracle_check.txt"
      d=$(ls -d /tmp/o/eval/$name/v* | tail -1)
      python3 experiments/oracle_audit.py --summary "$d" 2>&1 | tee -a "$OUT/oracle_check.txt"
      tar -czf "$OUT/$name.tgz" -C "$d" episodes
    done
    mps_stop ;;
  audit)  # #47: experiments/oracle_audit.py on the GPU, AUDIT_ARGS (e.g. "--task dice --object potato --n-grid 128
    # --size 0.03 --compare-cpu --reward backend=torch"): every fragment's role, d and IoU after each cut
    timeout ${LIMIT:-560} python3 experiments/oracle_audit.py --device cuda ${AUDIT_ARGS:-} 2>&1 | grep -v -i warn \
      | tee -a "$OUT/audit.txt" ;;
  split-bench)  # #49: a cut's split on the host against the Taichi kernels (benchmarks/split_device.py), 128^3 cake
    python3 benchmarks/split_device.py --device cuda --n-grid ${GRID:-128} --batch ${BATCH:-16} 2>&1 \
      | grep -v -i warn | tee -a "$OUT/split_bench.txt" ;;
  mppi-check)  # #47: MPPI at the demonstration settings (K=16, 2 iterations, horizon 1) beside the oracle, 64^3 with 5 cm
    # pieces, EPC episodes a cell (default 2: 54 each); a reward the planner beats the answer key on is one it games.
    # POLICIES (default oracle,mppi), NAME (the eval.name, default mppi64) and MPPI_ARGS (more overrides, e.g.
    # planner.push_last=true) compare planner settings on the same episodes
    mps_start
    t0=$(date +%s)
    timeout ${LIMIT:-560} python3 -m topocut.run stage=eval scale=paper device=cuda reward=torch sim.n_grid=64 \
      planner.iterations=2 planner.horizon=1 "eval.policies=[${POLICIES:-oracle,mppi}]" eval.train_seeds=1 \
      eval.jobs=${EVAL_JOBS:-12} eval.gifs=0 eval.videos=0 eval.episodes_per_cell=${EPC:-2} eval.name=${NAME:-mppi64} \
      logger=none progress=false outputs_root=/tmp/o ${MPPI_ARGS:-} \
      "eval.task_overrides={slice:{thickness:0.05},stick:{thickness:0.05,width:0.05},dice:{size:0.05}}" \
      2>&1 | grep -v -i warn | grep -v ticache | tail -40 | tee -a "$OUT/mppi_check.txt"
    echo "== wall $(( $(date +%s) - t0 )) s" | tee -a "$OUT/mppi_check.txt"
    d=$(ls -d /tmp/o/eval/${NAME:-mppi64}/v* | tail -1) && tar -czf "$OUT/${NAME:-mppi64}.tgz" -C "$d" episodes
    mps_stop ;;
  paper-cost)  # #49: benchmarks/paper_cost.py under MPS, scratch outputs in /tmp/pc (kept while the machine is warm:
    # run STAGES over back-to-back calls), its table and JSON to $OUT; PC_ARGS more options (e.g. --episodes 1)
    mps_start
    timeout ${LIMIT:-570} python3 benchmarks/paper_cost.py --out /tmp/pc --stages ${STAGES:-simulate mppi} \
      ${PC_ARGS:-} 2>&1 | grep -v -i warn | tail -40 | tee -a "$OUT/paper_cost.txt"
    cp /tmp/pc/paper_cost.json /tmp/pc/paper_cost.md "$OUT/" 2>/dev/null
    # the fits' Lightning reports (PC_ARGS="--set trainer.profiler=simple"), one per training run
    (cd /tmp/pc && find . -name fit-profile.txt | tar -czf "$OUT/profiles.tgz" -T -) 2>/dev/null
    mps_stop ;;
  reference)  # #54: the pyramid's own plane against three wrong planes (experiments/reference_check.py) at GRIDS
    for grid in ${GRIDS:-64 128}; do
      python3 experiments/reference_check.py pyramid --n-grid $grid --device cuda --json "$OUT/pyramid$grid.json" 2>&1 \
        | grep -v -i warn | tee -a "$OUT/reference.txt"
    done ;;
  reference-writing)  # #54: the scripted writer against a mirrored and a missing letter at n_grid 48 (~80 s)
    python3 experiments/reference_writing.py --n-grid 48 --device cuda 2>&1 | grep -v -i warn \
      | tee -a "$OUT/reference_writing.txt" ;;
  reference-scooping)  # #54: the scripted scoops against the scoop 2 cm short at n_grid 48 (~170 s)
    python3 experiments/reference_scooping.py --n-grid 48 --device cuda --variant reference --variant "2 cm short" 2>&1 \
      | grep -v -i warn | tee -a "$OUT/reference_scooping.txt" ;;
  multi-gpu)  # #53: PART=eval (the oracle's evaluation, EVAL_JOBS processes) or PART=demos (a stage=mppi multirun on the
    # joblib launcher, 12 cells) on GPU 0 alone and on every GPU of the node, nvidia-smi sampling each GPU's
    # utilisation every second beside them (EVAL_ARGS: overrides after the 64^3 defaults, e.g. the paper's 128^3 and 3 cm:
    # "sim.n_grid=128 eval.task_overrides={}"); PART=ddp (DDP_ARGS: overrides for the DDP runs alone, e.g. the
    # per-device batch halved so that both see the same global batch): stage=pretrain on the demos' merged dataset, one GPU and DDP on all
    mps_start
    ngpu=$(nvidia-smi -L | wc -l); all=$(seq -s, 0 $((ngpu - 1)))
    sets="0 $all"; [ "${PART:-eval}" = ddp ] || [ "$ngpu" = 1 ] && sets="$all"
    sets=${SETS:-$sets}  # e.g. SETS=0: GPU 0 alone again, once Taichi's kernel cache is warm
    for vis in $sets; do
      nvidia-smi --query-gpu=index,utilization.gpu --format=csv,noheader,nounits -lms 500 > /tmp/util.txt &
      mon=$!; t0=$(date +%s); tag=g${vis//,/}
      case "${PART:-eval}" in
        eval) CUDA_VISIBLE_DEVICES=$vis timeout ${LIMIT:-280} python3 -m topocut.run stage=eval scale=paper device=cuda \
            reward=torch sim.n_grid=64 sim.batch_size=4 "eval.policies=[oracle]" eval.train_seeds=1 \
            eval.jobs=${EVAL_JOBS:-12} eval.gifs=0 eval.videos=0 eval.episodes_per_cell=${EPC:-2} eval.name=$tag logger=none \
            progress=false outputs_root=/tmp/o \
            "eval.task_overrides={slice:{thickness:0.05},stick:{thickness:0.05,width:0.05},dice:{size:0.05}}" \
            ${EVAL_ARGS:-} \
            2>&1 | grep -v -i warn | tail -3 ;;
        demos) CUDA_VISIBLE_DEVICES=$vis timeout ${LIMIT:-280} python3 -m topocut.run -m stage=mppi \
            task=slice,stick,dice object=cake,cube,potato,ham hydra/launcher=joblib hydra.launcher.n_jobs=${JOBS:-12} \
            device=cuda sim.n_grid=64 sim.batch_size=16 planner.num_samples=16 planner.iterations=2 \
            planner.horizon=1 reward=torch data.episodes=${EPISODES:-3} task.max_cuts=5 logger=none progress=false \
            outputs_root=/tmp/d$tag 2>&1 | grep -v -i warn | tail -3 ;;
        ddp) python3 -m topocut.run stage=merge outputs_root=/tmp/dg${all//,/} logger=none progress=false 2>&1 | tail -2
          # F, then PDDP on it, on one GPU (seeds SEEDS: their spread) and under DDP on every GPU (seed 0); each
          # under its own outputs root so that bc trains on the F of the same trainer
          for tr in "trainer=gpu" "trainer=ddp trainer.devices=$ngpu"; do
            for seed in $([ "$tr" = trainer=gpu ] && echo ${SEEDS:-0 1} || echo 0); do
              root=/tmp/dd${tr//[^a-z0-9]/}$seed; mkdir -p $root && cp -r /tmp/dg${all//,/}/dataset $root/
              for st in pretrain bc; do
                t1=$(date +%s)
                CUDA_VISIBLE_DEVICES=$vis timeout ${LIMIT:-250} python3 -m topocut.run stage=$st $tr seed=$seed $([ "$tr" = trainer=gpu ] || echo ${DDP_ARGS:-}) \
                  $([ $st = bc ] && echo "stage.run.policies=[pddp]") trainer.max_epochs=${EPOCHS:-5} policy.train.max_epochs=${EPOCHS:-5} trainer.num_workers=2 \
                  logger=none progress=false outputs_root=$root 2>&1 | grep -v -i warn | grep -i "summary\|error" | tail -2
                echo "== $st $tr seed $seed: wall $(( $(date +%s) - t1 )) s; validation:" \
                  $(python3 -c "import glob, json, sys
for f in sorted(glob.glob(sys.argv[1] + '/checkpoint/*/v*/metrics.json')):
    m = json.load(open(f))['metrics']; print(f.split('/')[-3], {k: v for k, v in m.items() if 'val' in k})" $root)
              done
            done
          done ;;
      esac
      kill $mon
      echo "== ${PART:-eval} on GPUs $vis: wall $(( $(date +%s) - t0 )) s; mean utilisation % per GPU (samples > 0):" \
        $(awk -F', ' '{s[$1]+=$2; n[$1]++; if ($2 > 0) b[$1]++} END {for (g in s) printf "GPU%s %.0f (%d/%d) ", g, s[g]/n[g], b[g], n[g]}' /tmp/util.txt)
    done 2>&1 | tee -a "$OUT/multi_gpu.txt"
    mps_stop ;;
  demos)  # MPPI demonstrations through stage=mppi at 64^3, K=16, 2 iterations, horizon 1 (#31's per-cut figure)
    timeout ${LIMIT:-560} python3 -m topocut.run stage=mppi task=slice object=cake device=cuda sim.n_grid=64 \
      sim.batch_size=16 planner.num_samples=16 planner.iterations=2 planner.horizon=1 reward=torch \
      data.episodes=${EPISODES:-10} task.max_cuts=5 logger=none progress=false outputs_root=/tmp/o 2>&1 \
      | grep -v -i warn | tail -20 | tee -a "$OUT/demos.txt"
    find /tmp/o -path "*mppi*" -name status.json -exec cat {} \; | tee -a "$OUT/demos.txt" ;;
  paper)  # `make paper` (stage=all scale=paper) with PAPER_ARGS on top; resumes where the last call stopped (same
    # /tmp/o on a warm machine). Leaves the eval artifact, the runs' status files and the pipeline's log in $OUT.
    # MPS=1: under CUDA's Multi-Process Service, as `make paper` runs by default.
    if [ "${MPS:-0}" = 1 ]; then mps_start; fi
    t0=$(date +%s)
    timeout "${LIMIT:-570}" python3 -m topocut.run stage=all scale=paper device=cuda reward=torch trainer=gpu \
      logger=csv progress=false outputs_root=/tmp/o ${PAPER_ARGS:-} 2>&1 | grep -v -i "warn" | tail -120 \
      | tee -a "$OUT/paper.txt"
    echo "wall $(( $(date +%s) - t0 )) s" | tee -a "$OUT/paper.txt"
    if [ "${MPS:-0}" = 1 ]; then mps_stop; fi
    find /tmp/o/runs -name status.json | tar -czf "$OUT/runs.tgz" -T - 2>/dev/null
    [ -d /tmp/o/eval ] && tar -czf "$OUT/eval.tgz" -C /tmp/o eval
    for d in /tmp/o/dataset/*/v* /tmp/o/checkpoint/*/v*; do [ -f "$d/manifest.json" ] && echo "$d" \
      && cat "$d/manifest.json" | head -c 1500; done > "$OUT/manifests.txt" 2>/dev/null ;;
  bg)  # `make paper` with PAPER_ARGS (or BG_CMD, any command line, e.g. "python3 -m topocut.run stage=merge ...;
    # python3 -m topocut.run stage=all ...") started in its own process session, so that it outlives this call and
    # runs on until it ends or the machine goes back (30 min held); `watch` follows it. Its code is a copy of this
    # call's tree (/tmp/bg), which later calls' fresh /tmp/head cannot pull from under it. MPS=1: under CUDA's MPS.
    # Anchored at the start of a process's command line: the calling shell's own line ("bash -c ... BG_CMD=...
    # topocut.run ...") holds the words too, and an unanchored match refused every BG_CMD that named the module.
    if pgrep -f '^([^ ]*/)?python[0-9.]* -m topocut\.run' >/dev/null; then echo "bg: a run is already going"; exit 0; fi
    rm -rf /tmp/bg && cp -r "$PWD" /tmp/bg && cd /tmp/bg && export PYTHONPATH=/tmp/site:/tmp/bg
    if [ "${MPS:-0}" = 1 ]; then mps_start; fi
    rm -f /tmp/paper.log
    cmd=${BG_CMD:-"python3 -m topocut.run stage=all scale=paper device=cuda reward=torch trainer=gpu logger=csv \
      progress=false outputs_root=/tmp/o ${PAPER_ARGS:-}"}
    printf '%s\n' "$cmd" > /tmp/bg/cmd.sh  # a file: any quoting in BG_CMD survives
    setsid nohup bash -c "t0=\$(date +%s); timeout ${LIMIT:-3000} bash /tmp/bg/cmd.sh; \
      echo \"exit \$? after \$(( \$(date +%s) - t0 )) s\"" </dev/null >/tmp/paper.log 2>&1 &
    sleep 5; echo "bg: started (pid $!): $cmd"; tail -5 /tmp/paper.log ;;
  watch)  # wait up to WAIT s for the background run to end; its log's tail, the demonstration parts committed
    end=$(( $(date +%s) + ${WAIT:-540} ))
    while [ "$(date +%s)" -lt $end ] && ! grep -q "^exit " /tmp/paper.log 2>/dev/null; do sleep 10; done
    grep -v -i warn /tmp/paper.log | tail -${LINES_SHOWN:-30} | tee "$OUT/paper_tail.txt"
    cp /tmp/paper.log "$OUT/paper.log" 2>/dev/null
    echo "parts committed: $(ls -d /tmp/o/dataset/demos-*/v* 2>/dev/null | wc -l); episodes in them:" \
      "$(cat /tmp/o/dataset/demos-*/v*/episodes.jsonl 2>/dev/null | wc -l); in partial parts:" \
      "$(cat /tmp/o/dataset/demos-*/.partial-*/episodes.jsonl 2>/dev/null | wc -l)"
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader ;;
  bench-rest)
    for b in topology reward train train_policy; do
      [ -f benchmarks/$b.py ] && timeout 150 python3 benchmarks/$b.py --device cuda 2>&1 | tee "$OUT/bench_$b.txt"
    done
    timeout 120 python3 benchmarks/mppi.py --device cuda --K 16 --n-grid 128 2>&1 | tee "$OUT/bench_mppi.txt" ;;
  data)  # MPPI demonstrations on the GPU: 3 tasks x 2 objects x 2 episodes, merged into dataset/demos
    G="scale=smoke device=cuda sim.n_grid=64 sim.batch_size=8 planner.num_samples=8 planner.iterations=2
       topology.resolution=64 task.max_cuts=3 data.episodes=2 data.points_per_step=2048 outputs_root=/tmp/o
       logger=none progress=false"
    timeout 470 python3 -m topocut.run -m stage=mppi task=slice,stick,dice object=cake,donut $G 2>&1 \
      | grep -E "summary|Error|error" | tee "$OUT/data.txt"
    python3 -m topocut.run stage=merge $G 2>&1 | grep -E "summary|Error" | tee -a "$OUT/data.txt" ;;
  data2)  # larger MPPI set for Table 2: 3 tasks x 5 objects (donut unseen) x 3 episodes, 4 jobs at a time
    G="scale=smoke device=cuda sim.n_grid=64 sim.batch_size=8 planner.num_samples=8 planner.iterations=2
       topology.resolution=64 task.max_cuts=3 data.episodes=3 data.points_per_step=2048 outputs_root=/tmp/o
       logger=none progress=false"
    timeout 480 python3 -m topocut.run -m hydra/launcher=joblib hydra.launcher.n_jobs=4 stage=mppi \
      task=slice,stick,dice object=cake,potato,ham,cube,donut $G 2>&1 | grep -E "summary|Error|error" | tee "$OUT/data.txt"
    python3 -m topocut.run stage=merge $G 2>&1 | grep -E "summary|Error" | tee -a "$OUT/data.txt"
    tar -C /tmp -cf /tmp/o_dataset.tar o/dataset && ls -la /tmp/o_dataset.tar ;;
  table2)  # paper Table 2: graph model sort x noise x 128/256 points, PointNet 512/2048, on the merged set
    G="scale=smoke device=cuda trainer=gpu outputs_root=/tmp/o logger=none progress=false trainer.max_epochs=30
       model.num_layers=4 trainer.batch_size=16 trainer.num_workers=0"
    timeout 330 python3 -m topocut.run -m hydra/launcher=joblib hydra.launcher.n_jobs=4 stage=pretrain \
      model.sort=false,true model.noise=false,true model.num_points=128,256 $G 2>&1 | grep -E "summary|Error" \
      | tee "$OUT/table2.txt"
    timeout 220 python3 -m topocut.run -m hydra/launcher=joblib hydra.launcher.n_jobs=2 stage=pretrain model=pointnet \
      model.sort=false,true model.num_points=512 $G 2>&1 | grep -E "summary|Error" | tee -a "$OUT/table2.txt"
    python3 experiments/table2.py --root /tmp/o --out "$OUT/table2.md" ;;
  train)  # pretrain F, then PDDP / w/o perception / DP3 / 3DDA on the merged dataset
    G="scale=smoke device=cuda trainer=gpu outputs_root=/tmp/o logger=none progress=false"
    python3 -m topocut.run stage=merge $G 2>&1 | grep -E "summary|Error" | tee "$OUT/merge.txt"
    timeout 200 python3 -m topocut.run stage=pretrain $G trainer.max_epochs=40 model.num_layers=4 2>&1 \
      | grep -E "summary|Error" | tee "$OUT/train.txt"
    timeout 270 python3 -m topocut.run stage=bc $G policy.train.max_epochs=150 policy.net.n_blocks=12 \
      policy.train.batch_size=8 policy.train.lr=1e-3 2>&1 | grep -E "summary|Error" | tee -a "$OUT/train.txt"
    cp /tmp/o/checkpoint/perception/v*/metrics.json "$OUT/perception_metrics.json" ;;
  film)  # the evaluation films as it goes (eval.videos=1, eval.gifs=GIFS, default 1) on the GPU, in EVAL_JOBS worker
    # processes: the oracle, the heuristic and MPPI on smoke's two slice specs (and stick at 64^3: a push and a turn),
    # an MP4 per policy run, the first run's GIF per task and the cutting-sequence figure
    t0=$(date +%s)
    timeout ${LIMIT:-500} python3 -m topocut.run stage=eval scale=smoke device=cuda reward=torch sim.n_grid=${GRID:-64} \
      "eval.policies=[${POLICIES:-oracle,heuristic,mppi}]" "eval.tasks=[slice,stick]" eval.jobs=${EVAL_JOBS:-2} \
      eval.videos=1 eval.gifs=${GIFS:-1} logger=none progress=false outputs_root=/tmp/o ${EVAL_ARGS:-} 2>&1 | grep -v -i warn \
      | tail -25 | tee "$OUT/film.txt"
    echo "wall $(( $(date +%s) - t0 )) s" | tee -a "$OUT/film.txt"
    find /tmp/o/eval -name '*.mp4' -printf '%s %p\n' | tee -a "$OUT/film.txt"
    python3 - <<'PY' 2>&1 | tee -a "$OUT/film.txt"
import glob, json, os, imageio.v3 as iio
for v in sorted(glob.glob("/tmp/o/eval/table1/v*/videos/*/*.mp4")):
    e = json.load(open(v.replace("/videos/", "/episodes/").replace(".mp4", ".json")))
    print(v.split("/videos/")[1], iio.imread(v).shape, "cuts", e["num_cuts"], "R", round(e["final_reward"], 3),
          "video before JSON:", os.path.getmtime(v) <= os.path.getmtime(v.replace("/videos/", "/episodes/").replace(".mp4", ".json")))
for g in sorted(glob.glob("/tmp/o/eval/table1/v*/gifs/*")):
    print(g.split("/gifs/")[1], os.path.getsize(g), "bytes")
    if g.endswith(".gif"):  # <task>_<object>_<episode>_<run>.gif
        d, (key, run) = os.path.dirname(os.path.dirname(g)), os.path.basename(g)[:-4].rsplit("_", 1)
        j = f"{d}/episodes/{run}/{key}.json"
        print("  frames", len(iio.imread(g, index=None)), "cuts", json.load(open(j))["num_cuts"],
              "GIF before JSON:", os.path.getmtime(g) <= os.path.getmtime(j))
PY
    cp "$(find /tmp/o/eval -name '*.mp4' -path '*mppi*' | head -1)" "$OUT/" 2>/dev/null
    cp /tmp/o/eval/table1/v*/gifs/sequences.png "$OUT/" 2>/dev/null ;;
  eval)
    G="scale=smoke device=cuda sim.n_grid=64 sim.batch_size=8 planner.num_samples=8 topology.resolution=64
       outputs_root=/tmp/o logger=none progress=false eval.seen=[cake] eval.unseen=[donut]
       eval.tasks=[slice,stick,dice] eval.max_cuts=2 eval.num_points=2048"
    timeout 420 python3 -m topocut.run stage=eval $G 2>&1 | tail -30 | tee "$OUT/eval.txt"
    cp /tmp/o/eval/table1/v*/results.md /tmp/o/eval/table1/v*/results.csv /tmp/o/eval/table1/v*/results.png "$OUT/" ;;
  spread)  # run-to-run spread of a smoke eval on the GPU, three fresh processes (docs/evaluation.md)
    timeout 560 python3 benchmarks/eval_spread.py --runs 3 --timeout 250 --json "$OUT/spread.json" device=cuda \
      sim.n_grid=64 2>&1 | grep -v -i warn | tee "$OUT/spread.txt" ;;
  oracle)  # the oracle's pieces at 128^3 (docs/sim.md): states only (discover them here with --load on the CPU)
    timeout 400 python3 experiments/oracle_pieces.py --device cuda --n-grid 128 --save "$OUT/oracle" 2>&1 \
      | grep -v -i warn | tee "$OUT/oracle.txt" ;;
  *) echo "unknown phase $phase"; exit 2 ;;
esac
