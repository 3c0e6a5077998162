#!/bin/sh
# PostgreSQL for the detector replicas (compose.fleet), in the image base-image.sh makes with
# --postgres: run as the image's user (uid 10001, who reads the compose secrets), the data
# in $PGDATA (0700). The superuser `postgres` is reached through the container's own socket
# only; the replicas log in over TCP as $POSTGRES_USER, not a superuser, owner of
# $POSTGRES_DB, with the password of $POSTGRES_PASSWORD_FILE (set again at every start, so
# new credentials take effect on a kept volume).
set -eu
data=${PGDATA:-/var/lib/postgresql/data}
user=${POSTGRES_USER:-aesop}
db=${POSTGRES_DB:-aesop}
: "${POSTGRES_PASSWORD_FILE:?the password's file (a compose secret)}"
[ -r "$POSTGRES_PASSWORD_FILE" ] || { echo "postgres: cannot read $POSTGRES_PASSWORD_FILE" >&2; exit 1; }
sockets=/tmp
if [ ! -s "$data/PG_VERSION" ]; then
    initdb --pgdata="$data" --username=postgres --auth-local=trust --auth-host=reject \
        --encoding=UTF8 --locale=C.UTF-8 >/dev/null
    cat > "$data/pg_hba.conf" <<HBA
local all postgres trust
host $db $user 0.0.0.0/0 scram-sha-256
host $db $user ::/0 scram-sha-256
HBA
    fresh=1
fi
chmod 0700 "$data"
pg_ctl --pgdata="$data" --options="-c listen_addresses='' -k $sockets" --wait --silent start
psql --host=$sockets --username=postgres --dbname=postgres --quiet --set=ON_ERROR_STOP=1 \
    --set=user="$user" --set=db="$db" <<SQL
\set pw \`head -n1 "$POSTGRES_PASSWORD_FILE"\`
SELECT format('CREATE ROLE %I LOGIN NOSUPERUSER NOCREATEROLE NOCREATEDB', :'user')
  WHERE NOT EXISTS (SELECT FROM pg_roles WHERE rolname = :'user') \gexec
ALTER ROLE :"user" PASSWORD :'pw';
SELECT format('CREATE DATABASE %I OWNER %I', :'db', :'user')
  WHERE NOT EXISTS (SELECT FROM pg_database WHERE datname = :'db') \gexec
SQL
pg_ctl --pgdata="$data" --wait --silent stop
[ -z "${fresh:-}" ] || echo "postgres: a new cluster in $data, role $user, database $db"
exec postgres -D "$data" -c listen_addresses='*' -k "$sockets"
