#!/usr/bin/env bash
# A PIPELINE CHECK, not results: the six prompt variants through the local OpenAI-compatible TEST SERVER
# (tests/reasoner/fake_vlm.py answers every variant with the rules policy's decision read from the prompt; not a
# model, so the variants' rows differ only by noise), with every 20th answer truncated (invalid_json) to
# exercise re-prompting. Never commit its output as a variants sweep: docs/evaluation.md shows how to run the
# paper's ablation with a real model.
# Usage: scripts/eval_variants.sh [OUT] [extra `aermani eval` options, e.g. --output-mode both]
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PY:-.venv/bin/python}"
OUT="${1:-runs/eval-variants}"
shift || true
PORT="$("$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
LOG="$(mktemp)"
"$PY" -m tests.reasoner.fake_vlm --port "$PORT" --fault-every 20 --fault invalid_json >"$LOG" 2>&1 &
SERVER=$!
trap 'kill -INT "$SERVER" 2>/dev/null || true; wait "$SERVER" 2>/dev/null || true; rm -f "$LOG"' EXIT
for _ in $(seq 120); do grep -q "OpenAI-compatible" "$LOG" && break; sleep 0.5; done
grep -q "OpenAI-compatible" "$LOG" || { cat "$LOG"; echo "the test server did not start" >&2; exit 1; }
AERMANI_REASONER_API_KEY=none "$PY" -m aermani.cli eval --backend openai --model fake-vlm \
  --base-url "http://127.0.0.1:$PORT/v1" --variant unstructured,no_drt,drt_v1,drt_v2,drt_v3,full --episodes 1 \
  --parallel 3 --t-max 300 --out "$OUT" \
  --note "Numbers reflect the local OpenAI-compatible test server (tests/reasoner/fake_vlm.py: it answers every prompt with the rules policy's decision read from the prompt text alone, and every 20th answer is truncated to exercise re-prompting), not a real VLM." \
  "$@"
