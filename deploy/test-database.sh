#!/usr/bin/env bash
# A PostgreSQL server for the test suite's database tests, on Debian, as root: installs PostgreSQL if it is
# missing, starts its cluster, makes the role `overhang` (password `overhang`, allowed to create databases: the
# backup, restore and health tests make and drop their own) and the database `overhang_test`, and prints the
# line that points the tests at it:
#   url="$(bash deploy/test-database.sh)" && eval "$url" && .venv/bin/python -m pytest -q
set -euo pipefail
if ! command -v pg_lsclusters >/dev/null; then
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q >&2
  apt-get install -y -q --no-install-recommends postgresql >&2
fi
read -r version cluster _ < <(pg_lsclusters -h | head -n 1)
pg_ctlcluster "$version" "$cluster" start >&2 2>/dev/null || pg_ctlcluster "$version" "$cluster" status >/dev/null
port=$(pg_lsclusters -h | awk -v v="$version" -v c="$cluster" '$1 == v && $2 == c {print $3}')
psql_() { runuser -u postgres -- psql -p "$port" -q -v ON_ERROR_STOP=1 "$@"; }
psql_ -c "DO \$\$ BEGIN IF NOT EXISTS (SELECT FROM pg_roles WHERE rolname = 'overhang') THEN
          CREATE ROLE overhang LOGIN PASSWORD 'overhang'; END IF; END \$\$;" >&2
psql_ -c "ALTER ROLE overhang CREATEDB" >&2
psql_ -tc "SELECT 1 FROM pg_database WHERE datname = 'overhang_test'" | grep -q 1 \
  || runuser -u postgres -- createdb -p "$port" -O overhang overhang_test >&2
echo "export OVERHANG_TEST_POSTGRES_URL=postgresql+psycopg://overhang:overhang@127.0.0.1:$port/overhang_test"
