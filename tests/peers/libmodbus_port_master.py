"""libmodbus (Debian's libmodbus5, through ctypes) as a third-party RTU master on a serial master
port of the gateway (`[[server.serial]]`), for tests/peers.rs: the gateway is its slave, on the
pty it made and linked at PATH.

Usage: libmodbus_port_master.py PATH OP...
  OP   read:UNIT:ADDRESS:COUNT        Read Holding Registers (03), modbus_read_registers
       write:UNIT:ADDRESS:VALUE       Write Single Register (06), modbus_write_register; unit 0
                                      is a broadcast, which libmodbus sends without waiting
       writes:UNIT:ADDRESS:V1,V2,...  Write Multiple Registers (16), modbus_write_registers
  UNIT, ADDRESS, COUNT and the values are decimal.

Stdout, one line each, flushed, in order:
  op N                       the Nth OP begins (from 1)
  result VALUES...           the words read, or the value or the count written, in decimal
  result exception CODE      an exception reply, its code in decimal
  result none                no answer within the response timeout (or a broadcast)

libmodbus's debug mode prints the bytes it sends and receives on stdout too ([..] lines), which
the test reads as the wire. 9600 8N1; a pty ignores the format. Response timeout 1.5 s.
"""

import ctypes
import errno
import sys

from libmodbus_rtu import rtu_library

# libmodbus's errno base for Modbus exceptions (MODBUS_ENOBASE) and its codes past it.
MODBUS_ENOBASE = 112345678


LIBC = ctypes.CDLL(None)


def say(line):
    # libmodbus's debug lines are in C's stdout buffer: out first, so the order holds.
    LIBC.fflush(None)
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def main(path, ops):
    lib = rtu_library()
    lib.modbus_set_debug.argtypes = [ctypes.c_void_p, ctypes.c_int]
    lib.modbus_flush.argtypes = [ctypes.c_void_p]
    lib.modbus_set_response_timeout.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32]
    words = [ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.POINTER(ctypes.c_uint16)]
    lib.modbus_read_registers.argtypes = words
    lib.modbus_write_registers.argtypes = words
    lib.modbus_write_register.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_uint16]

    ctx = lib.modbus_new_rtu(path.encode(), 9600, b"N", 8, 1)
    if not ctx or lib.modbus_connect(ctx) != 0:
        sys.exit(f"libmodbus cannot open {path}")
    lib.modbus_set_response_timeout(ctx, 1, 500000)
    lib.modbus_set_debug(ctx, 1)

    for n, op in enumerate(ops, 1):
        say(f"op {n}")
        kind, unit, address, rest = op.split(":")
        unit, address = int(unit), int(address)
        lib.modbus_set_slave(ctx, unit)
        if kind == "read":
            count = int(rest)
            words = (ctypes.c_uint16 * count)()
            done = lib.modbus_read_registers(ctx, address, count, words)
            shown = " ".join(str(w) for w in words)
        elif kind == "write":
            done = lib.modbus_write_register(ctx, address, int(rest))
            shown = rest
        elif kind == "writes":
            values = [int(v) for v in rest.split(",")]
            done = lib.modbus_write_registers(
                ctx, address, len(values), (ctypes.c_uint16 * len(values))(*values)
            )
            shown = str(done)
        else:
            sys.exit(f"unknown op {op}")
        if done >= 0 and unit == 0:
            say("result none")
        elif done >= 0:
            say(f"result {shown}")
        else:
            code = ctypes.get_errno()
            if code > MODBUS_ENOBASE:
                say(f"result exception {code - MODBUS_ENOBASE}")
            elif code == errno.ETIMEDOUT:
                say("result none")
            else:
                say(f"result error {errno.errorcode.get(code, code)}")
            # Whatever came after the timeout is not the next request's answer.
            lib.modbus_flush(ctx)


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(f"usage: {sys.argv[0]} PATH OP...")
    main(sys.argv[1], sys.argv[2:])
