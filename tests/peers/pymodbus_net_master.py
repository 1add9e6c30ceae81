"""pymodbus's network clients as third-party masters for tests/peers.rs and tests/device_server.rs:
its TCP client with the RTU framer (RTU over TCP), its UDP client (Modbus UDP) or its plain Modbus
TCP client, against the gateway.

Usage: pymodbus_net_master.py rtu-over-tcp|udp|tcp HOST PORT UNIT

It writes holding register 5 = 4242, reads registers 5-6 back, then reads 17 registers from 0
(an answer the test knows), and prints one line per request, flushed:
  result FC VALUES...      the registers read, or "ok" for a write
  exception FC CODE        a Modbus exception
It exits non-zero on any transport error.
"""

import sys

from pymodbus import FramerType
from pymodbus.client import ModbusTcpClient, ModbusUdpClient

from replies import report, say


def main():
    kind, host, port, unit = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    if kind == "rtu-over-tcp":
        client = ModbusTcpClient(host, port=port, framer=FramerType.RTU, timeout=2, retries=0)
    elif kind == "udp":
        client = ModbusUdpClient(host, port=port, timeout=2, retries=0)
    else:
        client = ModbusTcpClient(host, port=port, timeout=2, retries=0)
    if not client.connect():
        sys.exit(f"cannot connect to {host}:{port}")
    report(6, client.write_register(5, 4242, device_id=unit))
    report(3, client.read_holding_registers(5, count=2, device_id=unit))
    report(3, client.read_holding_registers(0, count=3, device_id=unit))
    client.close()


if __name__ == "__main__":
    main()
