#!/usr/bin/env bash
# Source this: starts a throw-away PostgreSQL server on 127.0.0.1 (installing Debian's `postgresql` when no server is
# found), creates the user and database of the tests and exports DSSLAC_TEST_POSTGRES_URL. Idempotent: a running server
# in the same folder is reused. DSSLAC_PG_DIR and DSSLAC_PG_PORT move it.
set -euo pipefail
pg_dir="${DSSLAC_PG_DIR:-/tmp/sb3_dsslac_pg}"
pg_port="${DSSLAC_PG_PORT:-54329}"
pg_bin="$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -n 1 || true)"
if [ -z "$pg_bin" ]; then
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null
  pg_bin="$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -n 1)"
fi
# The server refuses to run as root: run it as the postgres user (created by the package), or as the caller otherwise
as_owner=()
if [ "$(id -u)" = 0 ]; then
  id postgres >/dev/null 2>&1 || useradd --system --home-dir "$pg_dir" postgres
  as_owner=(runuser -u postgres --)
fi
mkdir -p "$pg_dir"
[ "${#as_owner[@]}" = 0 ] || chown postgres "$pg_dir"
if [ ! -f "$pg_dir/data/PG_VERSION" ]; then
  "${as_owner[@]}" "$pg_bin/initdb" -D "$pg_dir/data" -U postgres --auth=trust >/dev/null
fi
if ! "${as_owner[@]}" "$pg_bin/pg_ctl" -D "$pg_dir/data" status >/dev/null 2>&1; then
  "${as_owner[@]}" "$pg_bin/pg_ctl" -D "$pg_dir/data" -l "$pg_dir/server.log" -w \
    -o "-c listen_addresses=127.0.0.1 -p $pg_port -k $pg_dir" start >/dev/null
fi
psql=("$pg_bin/psql" -h 127.0.0.1 -p "$pg_port" -U postgres -v ON_ERROR_STOP=1 -qtA)
if [ "$("${psql[@]}" -c "SELECT 1 FROM pg_roles WHERE rolname = 'dsslac'")" != 1 ]; then
  "${psql[@]}" -c "CREATE USER dsslac PASSWORD 'dsslac'"
fi
if [ "$("${psql[@]}" -c "SELECT 1 FROM pg_database WHERE datname = 'dsslac_test'")" != 1 ]; then
  "${psql[@]}" -c "CREATE DATABASE dsslac_test OWNER dsslac"
fi
export DSSLAC_TEST_POSTGRES_URL="postgresql://dsslac:dsslac@127.0.0.1:$pg_port/dsslac_test"
echo "PostgreSQL $("$pg_bin/postgres" --version | awk '{print $3}') on 127.0.0.1:$pg_port: DSSLAC_TEST_POSTGRES_URL=$DSSLAC_TEST_POSTGRES_URL"
