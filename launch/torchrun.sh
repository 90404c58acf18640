#!/usr/bin/env bash
# OMG pretraining with torchrun, on one machine or on each of N machines.
#
#   NODES=2 GPUS=8 NODE_RANK=0 MASTER_ADDR=10.0.0.1 launch/torchrun.sh configs/pretrain_giant.yaml
#   (run the same line on every node with its own NODE_RANK; one node: launch/torchrun.sh CONFIG)
#
# torchrun sets RANK, LOCAL_RANK, WORLD_SIZE, MASTER_ADDR and MASTER_PORT, from which
# Lightning's TorchElasticEnvironment takes the process layout. The accumulation is set so the
# global batch stays 256 (GLOBAL_BATCH) whatever NODES x GPUS is.
set -euo pipefail

CONFIG=${1:?usage: launch/torchrun.sh CONFIG [overrides...]}
shift
NODES=${NODES:-1}
GPUS=${GPUS:-$(nvidia-smi -L | wc -l)}
NODE_RANK=${NODE_RANK:-0}
MASTER_ADDR=${MASTER_ADDR:-127.0.0.1}
MASTER_PORT=${MASTER_PORT:-29500}
GLOBAL_BATCH=${GLOBAL_BATCH:-256}
BATCH=${BATCH:-$(python -c "import yaml,sys; print(yaml.safe_load(open(sys.argv[1]))['data']['batch_size'])" "$CONFIG")}
ACCUM=$(( GLOBAL_BATCH / (BATCH * NODES * GPUS) ))
if (( ACCUM < 1 || ACCUM * BATCH * NODES * GPUS != GLOBAL_BATCH )); then
  echo "global batch $GLOBAL_BATCH is not a multiple of $BATCH x $NODES nodes x $GPUS GPUs; set BATCH" >&2
  exit 2
fi

# NCCL's watchdog ends a process whose collective failed or outlived the process group's timeout
# (trainer.strategy.init_args.timeout, 30 min unless set) instead of leaving it hung on the GPU: 1 aborts
# the communicators and tears the process down (torchrun's own default for its workers, said here so
# that both launch paths run alike; a value already in the environment wins).
export TORCH_NCCL_ASYNC_ERROR_HANDLING=${TORCH_NCCL_ASYNC_ERROR_HANDLING:-1}

# c10d rendezvous (PyTorch's recommended multi-node backend): the node at MASTER_ADDR hosts the
# store, the others join it, and a node that starts late waits for the others (up to the
# rendezvous timeout) instead of failing; RDZV_ID tells concurrent jobs on the same port apart.
exec torchrun --nnodes "$NODES" --nproc-per-node "$GPUS" --node-rank "$NODE_RANK" \
  --rdzv-backend c10d --rdzv-endpoint "$MASTER_ADDR:$MASTER_PORT" --rdzv-id "${RDZV_ID:-omg}" \
  -m omg.cli fit --config "$CONFIG" \
  --trainer.num_nodes "$NODES" --trainer.devices "$GPUS" \
  --data.batch_size "$BATCH" --trainer.accumulate_grad_batches "$ACCUM" "$@"
