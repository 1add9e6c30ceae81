"""libmodbus (Debian's libmodbus5, through ctypes) as a third-party RTU slave for tests/hostile.rs:
a slave that finds the end of a request by its function's length, as libmodbus does, and takes
whatever bytes follow as the next request. The gateway must never send such bytes.

As in pymodbus_slave.py, two pty pairs joined by their master sides make a null-modem cable whose
two ends are /dev/pts paths: libmodbus opens one exactly as it would a USB adapter, the gateway the
other.

Stdout, one line each, flushed:
  ready PATH       libmodbus has its port open; PATH is the gateway's end of the cable
  request HEX      a request libmodbus took whole, its CRC good, before it acted on it
  synced           the answer to a line "sync" on stdin: every request the slave answered
                   before that line came is above it
The slave is device SLAVE_ID (and hears broadcasts) with 16 coils, 16 discrete inputs, and 16
holding and input registers, each register at 1000 + its address (input: 2000 +). The script
exits when its stdin closes, so it never outlives its test.
"""

import ctypes
import os
import select
import sys
import threading
import tty

from libmodbus_rtu import rtu_library

SLAVE_ID = 10
REGISTERS = 16
MAX_ADU = 256


class Mapping(ctypes.Structure):
    _fields_ = [
        ("nb_bits", ctypes.c_int),
        ("start_bits", ctypes.c_int),
        ("nb_input_bits", ctypes.c_int),
        ("start_input_bits", ctypes.c_int),
        ("nb_input_registers", ctypes.c_int),
        ("start_input_registers", ctypes.c_int),
        ("nb_registers", ctypes.c_int),
        ("start_registers", ctypes.c_int),
        ("tab_bits", ctypes.POINTER(ctypes.c_uint8)),
        ("tab_input_bits", ctypes.POINTER(ctypes.c_uint8)),
        ("tab_input_registers", ctypes.POINTER(ctypes.c_uint16)),
        ("tab_registers", ctypes.POINTER(ctypes.c_uint16)),
    ]


SAYING = threading.Lock()


def say(line):
    with SAYING:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


def cable(a, b):
    """Copy bytes both ways between two pty masters until the process ends."""
    while True:
        ready, _, _ = select.select([a, b], [], [])
        for src in ready:
            dst = b if src == a else a
            data = os.read(src, 4096)
            while data:
                data = data[os.write(dst, data) :]


def main():
    lib = rtu_library()
    lib.modbus_mapping_new.restype = ctypes.POINTER(Mapping)
    lib.modbus_receive.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
    lib.modbus_reply.argtypes = [
        ctypes.c_void_p,
        ctypes.c_void_p,
        ctypes.c_int,
        ctypes.POINTER(Mapping),
    ]

    slave_master, slave_end = os.openpty()
    gateway_master, gateway_end = os.openpty()
    # Raw before anyone opens them: a cooked pty echoes and rewrites bytes.
    tty.setraw(slave_end)
    tty.setraw(gateway_end)
    threading.Thread(target=cable, args=(slave_master, gateway_master), daemon=True).start()

    ctx = lib.modbus_new_rtu(os.ttyname(slave_end).encode(), 115200, b"N", 8, 2)
    if not ctx or lib.modbus_set_slave(ctx, SLAVE_ID) != 0 or lib.modbus_connect(ctx) != 0:
        sys.exit("libmodbus cannot open its end of the cable")
    mapping = lib.modbus_mapping_new(16, 16, REGISTERS, REGISTERS)
    for address in range(REGISTERS):
        mapping.contents.tab_registers[address] = 1000 + address
        mapping.contents.tab_input_registers[address] = 2000 + address

    def serve():
        request = (ctypes.c_uint8 * MAX_ADU)()
        while True:
            length = lib.modbus_receive(ctx, request)
            if length > 0:
                say(f"request {bytes(request[:length]).hex()}")
                lib.modbus_reply(ctx, request, length, mapping)

    threading.Thread(target=serve, daemon=True).start()
    say(f"ready {os.ttyname(gateway_end)}")
    # A request is said before it is answered: once a master has its answer, the line is in the
    # pipe, and "synced" said now comes after it.
    for line in iter(sys.stdin.readline, ""):
        if line.strip() == "sync":
            say("synced")


if __name__ == "__main__":
    main()
