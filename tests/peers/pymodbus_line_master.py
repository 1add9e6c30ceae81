"""pymodbus's serial client as the other master of a shared RS-485 line, for tests/listen.rs: it
masters the line the gateway only listens to (test-support's `tap`), polling the slave of
tests/peers/pymodbus_slave.py on PATH as a PLC or an inverter polls its meter.

Usage: pymodbus_line_master.py PATH

Stdin, one command a line (the script exits when stdin closes, so it never outlives its test):
  poll MS READ...   from now on, every MS milliseconds, each READ in turn (a round); `poll`
                    alone stops polling
  once READ         one read, between rounds
  write UNIT:ADDRESS:VALUE   Write Single Register (06), between rounds
where READ is FC:UNIT:ADDRESS:COUNT, FC one of 1 (coils), 2 (discrete inputs), 3 (holding
registers), 4 (input registers); all numbers decimal.

Stdout, one line each, flushed:
  ready                 the port is open and the commands are read
  polled N              N rounds done so far (after each round)
  result CMD OUTCOME    after a `once` or a `write`, CMD as given (its words joined by `_`), and
                        OUTCOME: the words or bits read (decimal, 0/1), the value written,
                        `exception CODE` (decimal), or `none` (no answer within the timeout)
A poll's outcome is not printed: the tap sees what the line carried.

The format is 115200 8N1: a pty refuses parity and cares for no baud rate. No retries, so each
request goes on the line once; a request nobody answers waits RESPONSE_TIMEOUT, longer than
the gateway's response_timeout in tests/listen.rs, so the gateway counts it as unanswered before
the next request comes.
"""

import os
import select
import sys
import time

from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient

RESPONSE_TIMEOUT = 0.5


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def read(client, spec):
    """One read by `spec` (FC:UNIT:ADDRESS:COUNT): its outcome as the `result` line says it."""
    function, unit, address, count = (int(part) for part in spec.split(":"))
    call = {
        1: client.read_coils,
        2: client.read_discrete_inputs,
        3: client.read_holding_registers,
        4: client.read_input_registers,
    }[function]
    try:
        reply = call(address, count=count, device_id=unit)
    except ModbusException:
        return "none"
    if reply.isError():
        return f"exception {reply.exception_code}"
    if function in (1, 2):
        return " ".join("1" if bit else "0" for bit in reply.bits[:count])
    return " ".join(str(word) for word in reply.registers)


def write(client, spec):
    unit, address, value = (int(part) for part in spec.split(":"))
    try:
        reply = client.write_register(address, value, device_id=unit)
    except ModbusException:
        return "none"
    if reply.isError():
        return f"exception {reply.exception_code}"
    return str(reply.registers[0])


def main(path):
    client = ModbusSerialClient(
        path,
        framer=FramerType.RTU,
        baudrate=115200,
        bytesize=8,
        parity="N",
        stopbits=1,
        timeout=RESPONSE_TIMEOUT,
        retries=0,
    )
    if not client.connect():
        sys.exit(f"cannot open {path}")
    say("ready")
    stdin = sys.stdin.fileno()
    pending = b""
    interval, reads = None, []
    next_round = time.monotonic()
    rounds = 0
    while True:
        wait = None if interval is None else max(0.0, next_round - time.monotonic())
        ready, _, _ = select.select([stdin], [], [], wait)
        if ready:
            data = os.read(stdin, 4096)
            if not data:
                break
            pending += data
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                words = line.decode().split()
                if not words:
                    continue
                if words[0] == "poll":
                    if len(words) == 1:
                        interval, reads = None, []
                    else:
                        interval, reads = int(words[1]) / 1000, words[2:]
                        next_round = time.monotonic()
                elif words[0] == "once":
                    say(f"result {'_'.join(words)} {read(client, words[1])}")
                elif words[0] == "write":
                    say(f"result {'_'.join(words)} {write(client, words[1])}")
                else:
                    sys.exit(f"unknown command {line!r}")
            continue
        if interval is not None and time.monotonic() >= next_round:
            # A round late (a command took its time), then the rounds go on from it: never
            # two rounds back to back to catch up.
            next_round = max(next_round, time.monotonic()) + interval
            for spec in reads:
                read(client, spec)
            rounds += 1
            say(f"polled {rounds}")
    client.close()


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} PATH")
    main(sys.argv[1])
