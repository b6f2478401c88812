#!/usr/bin/env bash
# Run here (with internet to the package registries) before benchmarks/device_check.sh: the packages the
# accelerator machine lacks (its python3 is 3.12 and holds a CUDA torch, numpy, scipy, pandas, pyarrow and
# the like, but no Ray), built for it and packed as one compressed file, .bundle/site.tar.xz, under the
# 64 MiB a call of the device tool may carry (Ray's wheel alone is 79 MB).
#
#   bash benchmarks/device_bundle.sh        # then carry .bundle (git ignores it)
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.bundle/' .git/info/exclude 2>/dev/null || echo '/.bundle/' >> .git/info/exclude
site=$(mktemp -d)
trap 'rm -rf "$site"' EXIT
python3 -m pip install -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  --target "$site" \
  ray==2.60.0 jsonschema jsonschema-specifications referencing rpds-py \
  gymnasium==1.2.2 farama-notifications pettingzoo==1.27.0 dm-tree==0.1.10 lz4 ormsgpack tensorboardX==2.6.5 \
  pydantic==2.14.4 pydantic-core==2.50.5 annotated-types typing-inspection typing-extensions
# what the checks never load (Java, Serve, the dashboard's web client, test suites) and the binaries'
# debugging symbols
rm -rf "$site"/ray/jars "$site"/ray/serve "$site"/ray/dashboard/client "$site"/ray/tests "$site"/ray/*/tests "$site"/bin
strip --strip-unneeded "$site"/ray/_raylet.so
strip "$site"/ray/core/src/ray/raylet/raylet "$site"/ray/core/src/ray/gcs/gcs_server
mkdir -p .bundle
tar -C "$site" -cf - . | xz -T1 -6 > .bundle/site.tar.xz
ls -l .bundle/site.tar.xz
