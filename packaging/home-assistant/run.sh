#!/bin/sh
# The Home Assistant add-on's entry point: turns the add-on's options (/data/options.json, which
# the Supervisor writes from the options in config.yaml) into the gateway's configuration,
# /data/gateway.toml, then runs the gateway on it. Needs sh and jq (both in the add-on's image
# and in the container image, where it is /usr/share/modbus-gateway/home-assistant/run.sh).
#
# OPTIONS and DATA override the two paths (for trying it out of Home Assistant).
set -eu

options=${OPTIONS:-/data/options.json}
data=${DATA:-/data}
config=$data/gateway.toml
gateway=${GATEWAY:-/usr/bin/modbus-gateway}

[ -r "$options" ] || { echo "run.sh: cannot read the add-on's options, $options" >&2; exit 2; }

# The password goes in a file of its own, readable by this account only: the gateway takes it
# from `mqtt.password_file`, never from its configuration.
umask 077
# The gateway reads the file's first line: a password of several lines would be cut.
if jq -e '(.mqtt_password // "") | test("[\r\n]")' "$options" >/dev/null; then
    echo "run.sh: option mqtt_password: a line break cannot be part of a password" >&2
    exit 2
fi
if jq -e '(.mqtt_password // "") != ""' "$options" >/dev/null; then
    jq -j '.mqtt_password' "$options" >"$data/mqtt-password"
elif [ -e "$data/mqtt-password" ]; then
    : >"$data/mqtt-password"  # a password removed from the options is not kept
fi

# Strings are written as JSON strings, which are TOML basic strings (same escapes); numbers are
# checked to be whole. A wrong option stops here, naming it.
toml=$(jq -r --arg password_file "$data/mqtt-password" '
    def whole($name):
        (.[$name] | tonumber? // null) as $n
        | if $n != null and $n == ($n | floor) then $n
          else error("option \($name): a whole number is needed, not \(.[$name] | tojson)") end;
    def text($name):
        if (.[$name] | type) == "string" and .[$name] != "" then .[$name] | tojson
        else error("option \($name): a text is needed, not \(.[$name] | tojson)") end;
    "# Written by the add-on from its options (/data/options.json) at every start: edit the",
    "# add-on'"'"'s configuration in Home Assistant, not this file.",
    "",
    "[server]",
    "listen = [\("0.0.0.0:\(whole("listen_port"))" | tojson)]",
    "",
    "[metrics]",
    "listen = \("0.0.0.0:\(whole("metrics_port"))" | tojson)",
    "",
    "[log]",
    "level = \(text("log_level"))",
    "",
    "[[bus]]",
    "name = \"line\"",
    "device = \(text("device"))",
    "baud = \(whole("baud"))",
    "parity = \(text("parity"))",
    "stop_bits = \(whole("stop_bits"))",
    "response_timeout = \("\(whole("response_timeout_ms"))ms" | tojson)",
    ((.slaves // [])[] |
        "",
        "[[bus.slave]]",
        "address = \(whole("address"))",
        (if (.template // "") != "" then "template = \(text("template"))" else empty end)),
    (if (.mqtt_url // "") != "" then
        "",
        "[mqtt]",
        "url = \(text("mqtt_url"))",
        (if (.mqtt_username // "") != "" then "username = \(text("mqtt_username"))"
         else empty end),
        (if (.mqtt_password // "") != "" then "password_file = \($password_file | tojson)"
         else empty end)
     else empty end)
' "$options") || exit 2
printf '%s\n' "$toml" >"$config"

# check-config names each bad key (of the file above: bus[0].baud is the option baud); then
# the gateway runs in this process, so that SIGTERM from the Supervisor reaches it.
"$gateway" --config "$config" check-config --quiet
exec "$gateway" --config "$config" run
