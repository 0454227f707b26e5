#!/bin/sh
# A private certificate authority and one certificate per tidee role, made with openssl.
#
#   deploy/secure/make_certs.sh [DIR] [ROUTER_HOST...]
#
# DIR (default: deploy/secure/certs, which the role files point at) receives ca.pem and ca.key,
# router.pem and router.key, and ROLE.pem and ROLE.key for each role in $ROLES (default: server
# agent viewer evaluator). A certificate's common name (CN) is its role: the router's access
# control (router.json5) tells clients apart by it. The router's certificate names the hosts
# clients reach it by (subjectAltName): the ROUTER_HOSTs, by default localhost 127.0.0.1 router
# (router: the compose service). An existing CA in DIR is kept, so more roles can be added later:
#
#   ROLES="agent2" deploy/secure/make_certs.sh
#
# Keys are P-256 EC keys (PKCS#8), certificates last $DAYS days (default 825). Keep ca.key off
# the machines that run tidee: whoever holds it can make a certificate for any role.
set -eu

dir=${1:-$(dirname "$0")/certs}
[ $# -gt 0 ] && shift
hosts=${*:-localhost 127.0.0.1 router}
roles=${ROLES:-server agent viewer evaluator}
days=${DAYS:-825}

command -v openssl >/dev/null || { echo "make_certs.sh: error: openssl is not installed" >&2; exit 1; }
mkdir -p "$dir"
umask 077
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1"; }

if [ ! -f "$dir/ca.pem" ]; then
    key "$dir/ca.key"
    openssl req -new -x509 -key "$dir/ca.key" -out "$dir/ca.pem" -days "$days" -subj "/CN=tidee-ca" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
fi

# sign NAME EXTENSIONS: NAME.key and NAME.pem with CN=NAME, signed by the CA
sign() {
    key "$dir/$1.key"
    openssl req -new -key "$dir/$1.key" -subj "/CN=$1" -out "$tmp/$1.csr"
    printf '%s\n' "basicConstraints=critical,CA:FALSE" "keyUsage=critical,digitalSignature" "$2" >"$tmp/$1.ext"
    openssl x509 -req -in "$tmp/$1.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" -CAcreateserial \
        -CAserial "$tmp/ca.srl" -out "$dir/$1.pem" -days "$days" -extfile "$tmp/$1.ext" 2>/dev/null
}

if [ ! -f "$dir/router.pem" ]; then
    san=""
    for h in $hosts; do
        case $h in
            *[!0-9.]*) san="$san,DNS:$h" ;;
            *) san="$san,IP:$h" ;;
        esac
    done
    sign router "extendedKeyUsage=serverAuth
subjectAltName=${san#,}"
fi
for role in $roles; do
    sign "$role" "extendedKeyUsage=clientAuth"
done
chmod 644 "$dir"/*.pem
echo "make_certs.sh: $dir: ca.pem, router.pem, $(echo "$roles" | sed 's/ /.pem, /g').pem and their .key files"
