#!/usr/bin/env bash
# The tests that reach transformers, on the oldest transformers that dyq declares (4.40.1, the version OpenVLA
# pins), laid over ./.venv through PYTHONPATH: build/transformers-4.40 holds transformers, its tokenizers and
# its hub client, everything else is ./.venv's. Run after scripts/setup.sh; arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
floor="$PWD/build/transformers-4.40"
if [ ! -f "$floor/.complete" ]; then
  rm -rf "$floor"
  .venv/bin/python -m pip install -q --target "$floor" --no-deps "transformers==4.40.1" "tokenizers>=0.19,<0.20" \
    "huggingface_hub>=0.19.3,<0.30" requests urllib3 idna certifi charset-normalizer
  touch "$floor/.complete"
fi
cd tests
export PYTHONPATH="$floor"
../.venv/bin/python -c "import transformers as t; assert t.__version__ == '4.40.1', t.__version__; print('transformers', t.__version__)"
../.venv/bin/python -m pytest -q -p no:cacheprovider test_transformers_versions.py test_quantize_model.py \
  test_quantize_cli.py test_weight_methods.py test_rotation.py test_smoothing.py test_sim_policy.py \
  test_sim_profile.py test_sim_closed_loop.py test_demo.py test_export.py "$@"
