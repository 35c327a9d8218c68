#!/bin/sh
# `pip install` inside an image build (Dockerfile): trusts the optional build secret pip_ca (a
# CA bundle, for networks whose proxy re-signs TLS; empty when none is given) and uses
# PIP_INDEX_URL only when the build sets it to something.
set -eu
if [ -s /run/secrets/pip_ca ]; then
    export PIP_CERT=/run/secrets/pip_ca
fi
if [ -z "${PIP_INDEX_URL:-}" ]; then
    unset PIP_INDEX_URL
fi
exec pip install "$@"
