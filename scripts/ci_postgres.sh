#!/usr/bin/env bash
# PostgreSQL for the job-store tests, as CI wants it (.ci/run sources this file).
#
# Where PostgreSQL is installed (this project's machines: 127.0.0.1:5432, trust authentication,
# database `test`), GREYFIT_TEST_DATABASE_URL points the tests at it; a stopped server is started,
# and a server that cannot be reached fails the run (exit 1) rather than skipping those tests
# quietly. Where it is not installed, the PostgreSQL tests are skipped and this says so.
# A GREYFIT_TEST_DATABASE_URL already set is used as it is.
#
# Overridable, for its own test (tests/test_ci_postgres.py) and for other machines:
#   GREYFIT_CI_PG_HOST (127.0.0.1), GREYFIT_CI_PG_PORT (5432), GREYFIT_CI_PG_CONF_DIR
#   (/etc/postgresql: one directory per installed version), GREYFIT_CI_PG_WAIT_SECONDS (30).
# Run directly (bash scripts/ci_postgres.sh) it only checks: exit 0 = the tests can go on.

PG_HOST=${GREYFIT_CI_PG_HOST:-127.0.0.1}
PG_PORT=${GREYFIT_CI_PG_PORT:-5432}
PG_CONF_DIR=${GREYFIT_CI_PG_CONF_DIR:-/etc/postgresql}
PG_WAIT_SECONDS=${GREYFIT_CI_PG_WAIT_SECONDS:-30}
pg_up() { (exec 3<>"/dev/tcp/$PG_HOST/$PG_PORT") 2>/dev/null; }

if [ -z "${GREYFIT_TEST_DATABASE_URL:-}" ] && [ -d "$PG_CONF_DIR" ] && [ -n "$(ls "$PG_CONF_DIR" 2>/dev/null)" ]; then
    export GREYFIT_TEST_DATABASE_URL="postgresql+psycopg://postgres@$PG_HOST:$PG_PORT/test"
    export GREYFIT_REQUIRE_POSTGRES=1   # the tests fail, not skip, if the server goes away
    if ! pg_up; then
        echo "ci: PostgreSQL is installed but not answering on $PG_HOST:$PG_PORT; starting it" >&2
        for version in $(ls "$PG_CONF_DIR"); do
            pg_ctlcluster --skip-systemctl-redirect "$version" main start >&2 || true
        done
        for _ in $(seq 1 "$PG_WAIT_SECONDS"); do pg_up && break; sleep 1; done
    fi
    if ! pg_up; then
        echo "ci: FAILED: PostgreSQL is installed here but no server answers on $PG_HOST:$PG_PORT" >&2
        echo "ci: start it (pg_ctlcluster --skip-systemctl-redirect \$(ls $PG_CONF_DIR) main start)" >&2
        echo "ci: or set GREYFIT_TEST_DATABASE_URL to a reachable server" >&2
        exit 1
    fi
    echo "ci: job-store tests also run on PostgreSQL ($GREYFIT_TEST_DATABASE_URL)" >&2
elif [ -z "${GREYFIT_TEST_DATABASE_URL:-}" ]; then
    echo "ci: no PostgreSQL on this machine: the PostgreSQL job-store tests will be skipped" >&2
fi
