"""pymodbus's RTU serial server as a third-party slave for tests/peers.rs.

A pty pair has a path on one side only, and both pymodbus and the gateway open their serial port by
path. So this makes two pty pairs and copies bytes between their master sides, a null-modem cable
whose two ends are /dev/pts paths: pymodbus opens one of them exactly as it would a USB adapter, and
the gateway gets the other.

Stdout, one line each, flushed:
  ready PATH       pymodbus has its port open; PATH is the gateway's end of the cable
  to-slave HEX     bytes the gateway put on the line (in whatever chunks the pty delivered)
  to-gateway HEX   bytes the slave answered with
Each wire line is printed before its bytes are passed on, so a test that has seen the bytes arrive
at one end finds them in its copy of this log soon after.

The slave is device SLAVE_ID with holding registers 0-9 holding 1000-1009; other addresses are
invalid (exception 02). The script exits when its stdin closes, so it never outlives its test.
"""

import asyncio
import os
import sys
import tty

from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

SLAVE_ID = 10
REGISTERS = [1000 + i for i in range(10)]


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def bridge(loop, src, dst, label):
    def forward():
        data = os.read(src, 4096)
        say(f"{label} {data.hex()}")
        while data:
            data = data[os.write(dst, data) :]

    loop.add_reader(src, forward)


async def main():
    loop = asyncio.get_running_loop()
    slave_master, slave_end = os.openpty()
    gateway_master, gateway_end = os.openpty()
    # Raw before anyone opens them: a cooked pty echoes and rewrites bytes.
    tty.setraw(slave_end)
    tty.setraw(gateway_end)
    # Both ends stay open here too, so a master never reads EIO while nobody holds the other side.
    bridge(loop, gateway_master, slave_master, "to-slave")
    bridge(loop, slave_master, gateway_master, "to-gateway")

    device = SimDevice(
        id=SLAVE_ID,
        simdata=[SimData(address=0, values=REGISTERS, datatype=DataType.REGISTERS)],
    )
    server = ModbusSerialServer(
        device,
        port=os.ttyname(slave_end),
        baudrate=115200,
        bytesize=8,
        parity="N",
        stopbits=2,
    )
    await server.serve_forever(background=True)

    stdin_closed = loop.create_future()

    def read_stdin():
        if not os.read(sys.stdin.fileno(), 4096) and not stdin_closed.done():
            stdin_closed.set_result(None)

    loop.add_reader(sys.stdin.fileno(), read_stdin)
    say(f"ready {os.ttyname(gateway_end)}")
    await stdin_closed
    await server.shutdown()


if __name__ == "__main__":
    asyncio.run(main())
