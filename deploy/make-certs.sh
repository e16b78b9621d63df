#!/bin/sh
# Make the certificates for mutual TLS between the router and every client:
# a private CA, the router's certificate, and one client certificate per user
# whose common name is the user (robot id or service name), which the router's
# access control matches with `cert_common_names`.
#
#   deploy/make-certs.sh [OUT_DIR] [ROUTER_NAMES] [USERS]
#   deploy/make-certs.sh deploy/secrets/tls "router,localhost,127.0.0.1" "r1 r2 r3 world central dslam assoc mcl evaluate monitor"
#
# Writes OUT_DIR/ca.pem (CA certificate, give it to everyone), ca-key.pem (keep
# it offline), router.pem + router-key.pem, and {user}.pem + {user}-key.pem.
# rustls (zenoh's TLS) rejects a leaf certificate without a subjectAltName
# naming the host it connects to, and one marked as a CA: every leaf gets
# basicConstraints=critical,CA:FALSE and a subjectAltName. Keys are EC P-256
# in PKCS#8; certificates last 825 days.
set -eu

OUT=${1:-deploy/secrets/tls}
ROUTER_NAMES=${2:-router,localhost,127.0.0.1}
USERS=${3:-r1 r2 r3 r4 r5 world central dslam assoc mcl evaluate monitor}
DAYS=825

mkdir -p "$OUT"
chmod 700 "$OUT"  # the files are made readable (0644) so a non-root container user can read them once
                  # bind-mounted as secrets; this folder guards them on the host

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# subjectAltName entries from a comma-separated list: IPs as IP:, the rest as DNS:
san() {
    echo "$1" | tr ',' '\n' | while read -r name; do
        [ -z "$name" ] && continue
        case "$name" in
            *[!0-9.]*) printf 'DNS:%s,' "$name" ;;
            *) printf 'IP:%s,' "$name" ;;
        esac
    done | sed 's/,$//'
}

# leaf NAME CN SAN USAGE: a certificate signed by the CA
leaf() {
    key "$OUT/$1-key.pem"
    openssl req -new -key "$OUT/$1-key.pem" -subj "/CN=$2" -out "$OUT/$1.csr"
    cat > "$OUT/$1.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=$4
subjectAltName=$3
EOF
    openssl x509 -req -in "$OUT/$1.csr" -CA "$OUT/ca.pem" -CAkey "$OUT/ca-key.pem" -CAcreateserial \
        -days "$DAYS" -sha256 -extfile "$OUT/$1.ext" -out "$OUT/$1.pem" 2>/dev/null
    rm -f "$OUT/$1.csr" "$OUT/$1.ext"
}

if [ ! -f "$OUT/ca.pem" ]; then
    key "$OUT/ca-key.pem"
    openssl req -x509 -new -key "$OUT/ca-key.pem" -subj "/CN=fleetslam CA" -days "$DAYS" -sha256 \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" -out "$OUT/ca.pem"
fi
leaf router "$(echo "$ROUTER_NAMES" | cut -d, -f1)" "$(san "$ROUTER_NAMES")" serverAuth,clientAuth
for user in $USERS; do
    leaf "$user" "$user" "DNS:$user" clientAuth
done
chmod 644 "$OUT"/*.pem
echo "certificates in $OUT: ca.pem, router.pem, $(echo $USERS | sed 's/ /.pem, /g').pem"
