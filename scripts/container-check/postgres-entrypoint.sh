#!/bin/sh
# Entry point of the stand-in PostgreSQL image (see build-standins.sh): what the official
# postgres image does with POSTGRES_USER, POSTGRES_PASSWORD and POSTGRES_DB on a first start
# (a cluster in $PGDATA with that superuser, password and database, reachable from other
# containers with a password), then the server in the foreground.
set -eu
PGDATA=${PGDATA:-/var/lib/postgresql/data}
BIN=/usr/lib/postgresql/15/bin
USER_NAME=${POSTGRES_USER:-postgres}
DATABASE=${POSTGRES_DB:-$USER_NAME}
mkdir -p "$PGDATA" /run/postgresql
chown -R postgres:postgres "$PGDATA" /run/postgresql
chmod 700 "$PGDATA"
if [ ! -s "$PGDATA/PG_VERSION" ]; then
    : "${POSTGRES_PASSWORD:?set POSTGRES_PASSWORD}"
    printf '%s\n' "$POSTGRES_PASSWORD" > /tmp/pwfile
    chown postgres /tmp/pwfile
    su postgres -c "$BIN/initdb -D '$PGDATA' --username='$USER_NAME' --pwfile=/tmp/pwfile --auth=scram-sha-256" >/dev/null
    rm -f /tmp/pwfile
    echo "host all all all scram-sha-256" >> "$PGDATA/pg_hba.conf"
    echo "listen_addresses = '*'" >> "$PGDATA/postgresql.conf"
    su postgres -c "$BIN/pg_ctl -D '$PGDATA' -o '-c listen_addresses=' -w start" >/dev/null
    if [ "$DATABASE" != postgres ]; then
        su postgres -c "PGPASSWORD='$POSTGRES_PASSWORD' $BIN/createdb -h /run/postgresql -U '$USER_NAME' '$DATABASE'"
    fi
    su postgres -c "$BIN/pg_ctl -D '$PGDATA' -m fast -w stop" >/dev/null
fi
exec su postgres -c "exec $BIN/postgres -D '$PGDATA'"
