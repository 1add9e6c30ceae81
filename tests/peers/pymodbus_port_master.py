"""pymodbus's serial client as a third-party master on a serial master port of the gateway
(`[[server.serial]]`), for tests/peers.rs: the gateway is its slave, on the pty it made and linked
at PATH.

Usage: pymodbus_port_master.py FRAMER PATH OP...
  FRAMER   rtu or ascii
  OP       read:UNIT:ADDRESS:COUNT        Read Holding Registers (03)
           write:UNIT:ADDRESS:VALUE       Write Single Register (06); unit 0 is a broadcast, sent
                                          without waiting for an answer
           writes:UNIT:ADDRESS:V1,V2,...  Write Multiple Registers (16)
  UNIT, ADDRESS, COUNT and the values are decimal.

Stdout, one line each, flushed, in order:
  op N                       the Nth OP begins (from 1)
  sent HEX                   a frame the client put on the line
  received HEX               bytes it read back (the packet its framer took)
  result VALUES...           the words read, or the value or the count written, in decimal
  result exception CODE      the slave's (here: the gateway's) exception, decimal
  result none                no answer within the timeout (or a broadcast, which has none)

The format is 9600 8N1: a pty refuses parity, and the gateway's end does not care. No retries,
so each request goes on the line once.
"""

import sys

from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient

RESPONSE_TIMEOUT = 1.5


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def trace(sending, data):
    say(f"{'sent' if sending else 'received'} {data.hex()}")
    return data


def run(client, op):
    kind, unit, address, rest = op.split(":")
    unit, address = int(unit), int(address)
    if kind == "read":
        reply = client.read_holding_registers(address, count=int(rest), device_id=unit)
    elif kind == "write":
        if unit == 0:
            client.write_register(address, int(rest), device_id=0, no_response_expected=True)
            return "none"
        reply = client.write_register(address, int(rest), device_id=unit)
    elif kind == "writes":
        values = [int(v) for v in rest.split(",")]
        reply = client.write_registers(address, values, device_id=unit)
    else:
        sys.exit(f"unknown op {op}")
    if reply.isError():
        return f"exception {reply.exception_code}"
    if kind == "read":
        return " ".join(str(word) for word in reply.registers)
    if kind == "write":
        return str(reply.registers[0])
    return str(reply.count)


def main(framer, path, ops):
    client = ModbusSerialClient(
        path,
        framer=FramerType.RTU if framer == "rtu" else FramerType.ASCII,
        baudrate=9600,
        bytesize=8,
        parity="N",
        stopbits=1,
        timeout=RESPONSE_TIMEOUT,
        retries=0,
        trace_packet=trace,
    )
    if not client.connect():
        sys.exit(f"cannot open {path}")
    for n, op in enumerate(ops, 1):
        say(f"op {n}")
        try:
            outcome = run(client, op)
        except ModbusException:
            outcome = "none"
        say(f"result {outcome}")
    client.close()


if __name__ == "__main__":
    if len(sys.argv) < 4 or sys.argv[1] not in ("rtu", "ascii"):
        sys.exit(f"usage: {sys.argv[0]} rtu|ascii PATH OP...")
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
