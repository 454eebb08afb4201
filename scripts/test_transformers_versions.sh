#!/usr/bin/env bash
# The tests that reach transformers, again on two 4.x releases laid over ./.venv (which has 5.x) through
# PYTHONPATH: 4.40.1, the oldest that dyq declares (the version OpenVLA pins), and 4.57.6, the last 4.x, with
# accelerate, which its quantized loading imports (dyq.DyQConfig needs 4.49 on). Each overlay, under
# build/transformers-<version>, holds transformers, its tokenizers and hub client; everything else is ./.venv's.
# Run after scripts/setup.sh; arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
TESTS=(test_transformers_versions.py test_quantize_model.py test_hf_quantizer.py test_quantize_cli.py
       test_weight_methods.py test_rotation.py test_smoothing.py test_sim_policy.py test_sim_profile.py
       test_sim_closed_loop.py test_demo.py test_export.py test_vla_backbones.py test_rms_norm.py)

# overlay VERSION PACKAGE...: build/transformers-VERSION with those packages (no dependencies), once.
overlay() {
  local version=$1 dir="$PWD/build/transformers-$1"
  shift
  if [ ! -f "$dir/.complete" ]; then
    rm -rf "$dir"
    .venv/bin/python -m pip install -q --target "$dir" --no-deps "transformers==$version" "$@" \
      requests urllib3 idna certifi charset-normalizer
    touch "$dir/.complete"
  fi
  echo "$dir"
}

run_on() {
  local version=$1 dir=$2
  shift 2
  echo "== transformers $version"
  (cd tests && PYTHONPATH="$dir" ../.venv/bin/python -c \
     "import transformers as t; assert t.__version__ == '$version', t.__version__" &&
   PYTHONPATH="$dir" ../.venv/bin/python -m pytest -q -p no:cacheprovider "${TESTS[@]}" "$@")
}

run_on 4.40.1 "$(overlay 4.40.1 "tokenizers>=0.19,<0.20" "huggingface_hub>=0.19.3,<0.30")" "$@"
run_on 4.57.6 "$(overlay 4.57.6 "tokenizers>=0.22,<0.23" "huggingface_hub>=0.34,<1.0" "accelerate==1.16.0")" "$@"
