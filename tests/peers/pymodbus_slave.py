"""pymodbus's serial server as a third-party slave for tests/peers.rs, with the framer named by
the one argument: `rtu` (the default), `ascii`, or `ascii-lower`: ASCII with the hex of every
reply in lower case (pymodbus sends upper case, as the spec has it; some devices do not).

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

The slave is device SLAVE_ID with four separate tables (coils and discrete inputs addressed by the
bit, as the spec has it); other addresses are invalid (exception 02):
  coils 0-15             on where the address is a multiple of 3 (0, 3, 6, 9, 12, 15)
  discrete inputs 0-15   on where the address is odd
  holding registers 0-9  1000-1009
  input registers 0-9    2000-2009
The script exits when its stdin closes, so it never outlives its test.

The serial format is 8N2 for either framing, as the gateway's side is set. A pty refuses parity
(EINVAL), so ASCII's default 7E1 cannot be had; and it keeps 8 data bits whatever it is asked: 7
data bits take once, read back as 8, and pyserial's next reconfiguration (pymodbus sets a timeout
after opening) fails with EINVAL. ASCII characters are 7-bit, so they cross unchanged anyway.
"""

import asyncio
import os
import sys
import tty

from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

SLAVE_ID = 10
COILS = [i % 3 == 0 for i in range(16)]
DISCRETE_INPUTS = [i % 2 == 1 for i in range(16)]
REGISTERS = [1000 + i for i in range(10)]
INPUT_REGISTERS = [2000 + i for i in range(10)]
# argument: (framer, what becomes of each reply frame on its way out)
FRAMERS = {
    "rtu": (FramerType.RTU, None),
    "ascii": (FramerType.ASCII, None),
    "ascii-lower": (
        FramerType.ASCII,
        lambda sending, frame: frame.lower() if sending else frame,
    ),
}


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


async def serve(device, framer=FramerType.RTU, trace_packet=None):
    """Serve `device` (a pymodbus SimDevice) with `framer` on one end of a pty cable, printing
    `ready PATH` and the wire as above, until stdin closes. Also the server of sibling scripts
    that load other tables (pymodbus_values_slave.py)."""
    loop = asyncio.get_running_loop()
    slave_master, slave_end = os.openpty()
    gateway_master, gateway_end = os.openpty()
    # Raw before anyone opens them: a cooked pty echoes and rewrites bytes.
    tty.setraw(slave_end)
    tty.setraw(gateway_end)
    # Both ends stay open here too, so a master never reads EIO while nobody holds the other side.
    bridge(loop, gateway_master, slave_master, "to-slave")
    bridge(loop, slave_master, gateway_master, "to-gateway")

    server = ModbusSerialServer(
        device,
        framer=framer,
        trace_packet=trace_packet,
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


async def main(framer, trace_packet):
    device = SimDevice(
        id=SLAVE_ID,
        # (coils, discrete inputs, holding registers, input registers)
        simdata=(
            [SimData(address=0, values=COILS, datatype=DataType.BITS)],
            [SimData(address=0, values=DISCRETE_INPUTS, datatype=DataType.BITS)],
            [SimData(address=0, values=REGISTERS, datatype=DataType.REGISTERS)],
            [SimData(address=0, values=INPUT_REGISTERS, datatype=DataType.REGISTERS)],
        ),
    )
    await serve(device, framer, trace_packet)


if __name__ == "__main__":
    if len(sys.argv) > 2 or (len(sys.argv) == 2 and sys.argv[1] not in FRAMERS):
        sys.exit(f"usage: {sys.argv[0]} [{'|'.join(FRAMERS)}]")
    asyncio.run(main(*FRAMERS[sys.argv[1] if len(sys.argv) > 1 else "rtu"]))
