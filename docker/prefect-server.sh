#!/bin/sh
# Entry point of the Prefect server in docker/compose.yaml: `prefect-server.sh COMMAND...`.
# Whoever reaches the Prefect API can create a deployment that runs code on the worker, so a
# server published beyond this host (MATEQA_PUBLISH_ADDRESS other than loopback) must ask for
# the auth string (PREFECT_SERVER_API_AUTH_STRING, "user:password"); without one it does not
# start. An empty auth string is no auth string (Prefect would refuse every request).
set -eu
address="${MATEQA_PUBLISH_ADDRESS:-127.0.0.1}"
if [ -z "${PREFECT_SERVER_API_AUTH_STRING:-}" ]; then
    unset PREFECT_SERVER_API_AUTH_STRING
    case "$address" in
        127.*|::1|localhost) ;;
        *)
            echo "prefect-server: published on $address, beyond this host, without an auth" \
                 "string; set PREFECT_API_AUTH_STRING=user:password where you run" \
                 "docker compose (see the README)" >&2
            exit 2
            ;;
    esac
fi
exec "$@"
