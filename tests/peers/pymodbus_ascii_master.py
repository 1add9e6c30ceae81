"""pymodbus's serial client as a third-party Modbus ASCII master for tests/peers.rs: it talks to
the simulated drives of config/demo-ascii.toml (those of config/demo.toml on a 9600 7E1 ASCII
line) that `modbus-gateway simulate` serves on the pty at PATH, the one argument.

Stdout, one line each, flushed:
  sent HEX                          bytes the client put on the line
  received HEX                      bytes it read back (in whatever chunks the pty delivered)
  result UNIT FC ADDRESS VALUES...  a request's outcome: the words read or written, in decimal
  result UNIT FC ADDRESS exception CODE
  result UNIT FC ADDRESS failed TEXT  no answer, or one pymodbus could not take
UNIT and CODE are decimal, FC and ADDRESS upper-case hex (FC two digits, ADDRESS four).

The serial format is 8N1 whatever the bus's 7E1: a pty refuses parity (EINVAL), and 7 data bits
take once, read back as 8, and fail pyserial's next reconfiguration. ASCII characters are 7-bit,
so they cross a pty unchanged either way. No retries, so each request goes on the wire once.
"""

import sys

from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient

RESPONSE_TIMEOUT = 1.0


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


class LoggedClient(ModbusSerialClient):
    """The client, with every byte it sends and receives on stdout."""

    def send(self, request, addr=None):
        say(f"sent {request.hex()}")
        return super().send(request, addr)

    def recv(self, size):
        data = super().recv(size)
        if data:
            say(f"received {data.hex()}")
        return data


def result(unit, fc, address, call):
    head = f"result {unit} {fc:02X} {address:04X}"
    try:
        reply = call()
    except ModbusException as e:
        say(f"{head} failed {e}")
        return
    if reply.isError():
        say(f"{head} exception {reply.exception_code}")
    elif fc == 0x06:
        say(f"{head} {reply.registers[0]}")
    else:
        say(f"{head} {' '.join(str(word) for word in reply.registers)}")


def main(path):
    client = LoggedClient(
        path,
        framer=FramerType.ASCII,
        baudrate=9600,
        bytesize=8,
        parity="N",
        stopbits=1,
        timeout=RESPONSE_TIMEOUT,
        retries=0,
    )
    if not client.connect():
        sys.exit(f"cannot open {path}")
    # Each drive's identifying code (2103H).
    for unit in (1, 2, 3):
        result(
            unit,
            0x03,
            0x2103,
            lambda: client.read_holding_registers(0x2103, count=1, device_id=unit),
        )
    # Unit 2's frequency reference (2001H) = 25.00 Hz, then its running value (3001H).
    result(
        2, 0x06, 0x2001, lambda: client.write_register(0x2001, 2500, device_id=2)
    )
    result(
        2, 0x03, 0x3001, lambda: client.read_holding_registers(0x3001, count=1, device_id=2)
    )
    # 17 words, one more than a Goodrive reads at once.
    result(
        2, 0x03, 0x3000, lambda: client.read_holding_registers(0x3000, count=17, device_id=2)
    )
    client.close()


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} PATH")
    main(sys.argv[1])
