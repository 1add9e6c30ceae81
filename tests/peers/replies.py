"""How the pymodbus master scripts of tests/peers print what they got, one line per request, for
the Rust tests to read: "result 3 1000 1001", "result 6 ok" or "exception 6 1"."""

import sys


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def report(fc, response):
    if response.isError():
        say(f"exception {fc} {response.exception_code}")
    elif hasattr(response, "registers") and fc == 3:
        say(f"result {fc} " + " ".join(str(r) for r in response.registers))
    else:
        say(f"result {fc} ok")
