"""pymodbus's Modbus TCP server: where tests/device_link.rs's gateway expects a serial device server
in raw mode (a converter left in its "Modbus TCP gateway" mode), and the Modbus TCP device of
tests/tcp_device.rs. Device 1 has holding and input registers 0-19 at 7, coils and discrete inputs
0-15 off.

Usage: pymodbus_tcp_server.py [tls CERT KEY CA]: with `tls`, pymodbus's Modbus/TCP Security server
(ModbusTlsServer), presenting CERT and KEY and requiring a client certificate that chains to CA.

Stdout, one line, flushed: `listening PORT` once the server accepts connections on 127.0.0.1:PORT
(a free port). The script exits when its stdin closes, so it never outlives its test.
"""

import asyncio
import socket
import sys

import ssl

from pymodbus.server import ModbusTcpServer, ModbusTlsServer
from pymodbus.simulator import DataType, SimData, SimDevice


def free_port():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


async def main():
    loop = asyncio.get_running_loop()
    bits = [SimData(address=0, values=[False] * 16, datatype=DataType.BITS)]
    registers = [SimData(address=0, values=[7] * 20, datatype=DataType.REGISTERS)]
    device = SimDevice(id=1, simdata=(bits, bits, registers, registers))
    port = free_port()
    if len(sys.argv) == 5 and sys.argv[1] == "tls":
        _, _, cert, key, ca = sys.argv
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.load_cert_chain(cert, key)
        context.load_verify_locations(ca)
        context.verify_mode = ssl.CERT_REQUIRED
        server = ModbusTlsServer(device, address=("127.0.0.1", port), sslctx=context)
    else:
        server = ModbusTcpServer(device, address=("127.0.0.1", port))
    await server.serve_forever(background=True)
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.1):
                break
        except OSError:
            await asyncio.sleep(0.02)
    sys.stdout.write(f"listening {port}\n")
    sys.stdout.flush()
    stdin_closed = loop.create_future()

    def read_stdin():
        import os

        if not os.read(sys.stdin.fileno(), 4096) and not stdin_closed.done():
            stdin_closed.set_result(None)

    loop.add_reader(sys.stdin.fileno(), read_stdin)
    await stdin_closed
    await server.shutdown()


if __name__ == "__main__":
    asyncio.run(main())
