"""pymodbus's RTU serial server holding the plant values of tests/values_peers.rs, on the pty cable
of pymodbus_slave.py (the same stdout: `ready PATH`, then the wire both ways).

One argument, JSON: the slave's id and what each of its four tables holds, as runs of consecutive
addresses, e.g.
  {"slave": 7, "holding": [[0, [17562, 20480]]], "input": [[0, [1]], [10, [2]]],
   "coil": [[3, [1, 0]]], "discrete": [[7, [1, 0]]]}
Registers are 16-bit words exactly as they go on the wire (high byte first); coils and discrete
inputs are 0 or 1, and the ones not listed are off. A register not listed is not there: a read
that touches it is answered with exception 02 (illegal data address), as real devices answer a
read across a hole in their map. Every table needs at least one run (pymodbus's rule).
The script exits when its stdin closes, so it never outlives its test.
"""

import asyncio
import json
import sys

from pymodbus.simulator import DataType, SimData, SimDevice

from pymodbus_slave import serve


def runs(table, datatype):
    if not table:
        sys.exit("every table needs at least one run of addresses")
    convert = bool if datatype == DataType.BITS else int
    return [
        SimData(address=first, values=[convert(v) for v in values], datatype=datatype)
        for first, values in table
    ]


def main():
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} TABLES_JSON")
    tables = json.loads(sys.argv[1])
    device = SimDevice(
        id=tables["slave"],
        # (coils, discrete inputs, holding registers, input registers)
        simdata=(
            runs(tables["coil"], DataType.BITS),
            runs(tables["discrete"], DataType.BITS),
            runs(tables["holding"], DataType.REGISTERS),
            runs(tables["input"], DataType.REGISTERS),
        ),
    )
    asyncio.run(serve(device))


if __name__ == "__main__":
    main()
