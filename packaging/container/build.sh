#!/usr/bin/env bash
# Builds the container image with buildah (else Podman, else Docker), from no base image: the
# release binary (built if it is not up to date; without cargo, target/release's), the shared libraries `ldd` lists for it, and, for the Home Assistant
# add-on's run script (packaging/home-assistant/run.sh), dash and jq from the Debian packages of
# this machine's distribution (apt-get download: the package lists must be there). Then the
# shipped templates, a default configuration (config/demo.toml on all addresses) and the
# account. No registry is needed.
#
#   packaging/container/build.sh [TAG]      default TAG: modbus-gateway:VERSION (Cargo.toml's)
#   BUILDER=podman packaging/container/build.sh   (or docker): the builder, if not buildah
#
# Prints the image's tag on its last line.
set -euo pipefail
cd "$(dirname "$0")/../.."

fail() {
    echo "build.sh: $*" >&2
    exit 1
}
# BUILDER=buildah|podman|docker chooses; else the first of them found.
builder=${BUILDER:-}
for candidate in buildah podman docker; do
    [ -z "$builder" ] && command -v "$candidate" >/dev/null && builder=$candidate
done
[ -n "$builder" ] || fail "buildah, podman or docker is needed (Debian: apt-get install buildah)"

# The package's version: the first version line of Cargo.toml, the [package] table's.
version=$(sed -n 's/^version = "\([^"]*\)"$/\1/p' Cargo.toml | head -n 1)
[ -n "$version" ] || fail "Cargo.toml has no version"
tag=${1:-modbus-gateway:$version}

if command -v cargo >/dev/null; then
    target_dir=$(cargo metadata --format-version 1 --no-deps |
        sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p')
    [ -n "$target_dir" ] || fail "cargo metadata names no target directory"
    # The daemon as shipped (no test-util), as debian/build-deb builds it.
    cargo build --release --locked -p modbus-gatewayd --bin modbus-gateway >&2
else
    target_dir=$PWD/target
fi
bin=$target_dir/release/modbus-gateway
[ -x "$bin" ] || fail "no $bin: build it first (cargo build --release --locked)"

context=$target_dir/container
rootfs=$context/rootfs
rm -rf "$rootfs" "$context/journal" "$context/debroot"
mkdir -p "$rootfs" "$context/journal" "$context/debs" "$context/debroot"

# PATH, and the libraries the dynamic loader would load for it, at the same paths (the loader
# itself included). LIBRARY_PATH: where else to look (the Debian packages' libraries).
copy_with_libraries() { # source destination [LIBRARY_PATH]
    install -D -m 755 "$1" "$rootfs$2"
    local libraries
    libraries=$(LD_LIBRARY_PATH=${3:-} ldd "$1") || fail "ldd $1: $libraries"
    grep -q 'not found' <<<"$libraries" && fail "ldd $1: $libraries"
    for library in $(grep -o '/[^ ]*' <<<"$libraries"); do
        local at=$library
        # A library found on LIBRARY_PATH goes where the package installs it.
        [ -n "${3:-}" ] && at=${library#"$context/debroot"}
        # With its own mode: the loader must stay executable.
        local file
        file=$(realpath "$library")
        [ -e "$rootfs$at" ] || install -D -m "$(stat -c %a "$file")" "$file" "$rootfs$at"
    done
}
copy_with_libraries "$bin" /usr/bin/modbus-gateway

# The Debian packages of the add-on's shell and JSON reader, downloaded once into the context.
packages=(dash jq libjq1 libonig5)
(
    cd "$context/debs"
    for package in "${packages[@]}"; do
        ls "${package}"_*.deb >/dev/null 2>&1 && continue
        # As root, apt would warn that its sandbox user cannot write here.
        apt-get -q -o APT::Sandbox::User="$(id -un)" download "$package" >&2 ||
            fail "apt-get download $package failed (run apt-get update first?)"
    done
)
for deb in "$context"/debs/*.deb; do dpkg-deb -x "$deb" "$context/debroot"; done
multiarch=$(dpkg-architecture -qDEB_HOST_MULTIARCH 2>/dev/null || gcc -print-multiarch)
debroot_libs=$context/debroot/usr/lib/$multiarch:$context/debroot/lib/$multiarch
copy_with_libraries "$context/debroot/bin/dash" /bin/dash "$debroot_libs"
ln -s dash "$rootfs/bin/sh"
copy_with_libraries "$context/debroot/usr/bin/jq" /usr/bin/jq "$debroot_libs"

# The account: modbus-gateway (65532, as distroless images' nonroot), in dialout for serial
# devices. Name service: files (/etc/hosts, which the runtime writes), then DNS.
install -d -m 755 "$rootfs/etc"
printf 'root:x:0:0:root:/root:/usr/sbin/nologin\nmodbus-gateway:x:65532:65532:modbus-gateway:/nonexistent:/usr/sbin/nologin\n' \
    >"$rootfs/etc/passwd"
printf 'root:x:0:\ndialout:x:20:modbus-gateway\nmodbus-gateway:x:65532:\n' >"$rootfs/etc/group"
printf 'passwd: files\ngroup: files\nhosts: files dns\n' >"$rootfs/etc/nsswitch.conf"

# The default configuration: the demo, on every address of the container.
install -d -m 755 "$rootfs/etc/modbus-gateway"
{
    echo "# The container image's default configuration: the README's demo (config/demo.toml),"
    echo "# served on all addresses. Mount your own at /etc/modbus-gateway (docs/install.md)."
    echo
    sed 's/"127\.0\.0\.1:\([0-9]*\)"/"0.0.0.0:\1"/' config/demo.toml
} >"$rootfs/etc/modbus-gateway/gateway.toml"
grep -q '"0.0.0.0:5020"' "$rootfs/etc/modbus-gateway/gateway.toml" ||
    fail "config/demo.toml no longer listens on 127.0.0.1:5020: see the sed above"
install -D -m 644 -t "$rootfs/usr/share/modbus-gateway/templates" config/templates/*.toml
install -D -m 755 packaging/home-assistant/run.sh \
    "$rootfs/usr/share/modbus-gateway/home-assistant/run.sh"
install -D -m 644 -t "$rootfs/usr/share/doc/modbus-gateway" LICENSE-MIT LICENSE-APACHE
# The mount points a runtime fills, for a read-only root.
install -d -m 755 "$rootfs/proc" "$rootfs/dev" "$rootfs/sys" "$rootfs/data"
install -d -m 1777 "$rootfs/tmp"

# The Docker format: OCI images have no HEALTHCHECK.
case $builder in
buildah) format=(--format docker --layers=false) ;;
podman) format=(--format docker) ;;
docker) format=() ;;
esac
"$builder" build --quiet "${format[@]}" --build-arg "VERSION=$version" \
    -f packaging/container/Containerfile -t "$tag" "$context" >&2
echo "$tag"
