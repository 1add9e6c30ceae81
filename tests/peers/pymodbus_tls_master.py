"""pymodbus's TLS client (Modbus/TCP Security) as a third-party master for tests/peers.rs, with a
certificate of the README's walkthrough.

Usage: pymodbus_tls_master.py HOST PORT CA CERT KEY UNIT OPERATION...
  OPERATION is "read ADDRESS COUNT" (03) or "write ADDRESS VALUE" (06); numbers in any Python
  base ("0x2001").

The gateway's certificate must chain to CA and carry HOST (an address or a name); the master
presents CERT with KEY. It prints one line per operation, flushed:
  result 3 VALUES...      the registers read
  result 6 ok             a write answered
  exception FC CODE       a Modbus exception
It exits non-zero if the handshake fails or on any transport error.

It uses the asynchronous client: pymodbus 3.16's synchronous ModbusTlsClient wraps its socket
without server_hostname, so a context that checks the server's name cannot be used with it.
"""

import asyncio
import ssl
import sys

from pymodbus.client import AsyncModbusTlsClient

from replies import report


async def main():
    host, port, ca, cert, key, unit = sys.argv[1:7]
    port, unit = int(port), int(unit)
    operations = sys.argv[7:]
    sslctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=ca)
    sslctx.load_cert_chain(cert, key)
    client = AsyncModbusTlsClient(host, port=port, sslctx=sslctx, timeout=5, retries=0)
    if not await client.connect():
        sys.exit(f"cannot connect to {host}:{port} over TLS")
    while operations:
        operation, address, value = operations[:3]
        operations = operations[3:]
        address, value = int(address, 0), int(value, 0)
        if operation == "read":
            report(3, await client.read_holding_registers(address, count=value, device_id=unit))
        elif operation == "write":
            report(6, await client.write_register(address, value, device_id=unit))
        else:
            sys.exit(f"unknown operation {operation!r}")
    client.close()


if __name__ == "__main__":
    asyncio.run(main())
