"""Debian's libmodbus5 through ctypes, for the test scripts that drive it (libmodbus_slave.py,
libmodbus_port_master.py): the library with the prototypes of its RTU context set, so that a
script sets only those of the calls it makes beyond them."""

import ctypes


def rtu_library():
    """libmodbus.so.5 (errno kept for ctypes.get_errno), with modbus_new_rtu, modbus_set_slave
    and modbus_connect typed."""
    lib = ctypes.CDLL("libmodbus.so.5", use_errno=True)
    lib.modbus_new_rtu.restype = ctypes.c_void_p
    lib.modbus_new_rtu.argtypes = [
        ctypes.c_char_p,
        ctypes.c_int,
        ctypes.c_char,
        ctypes.c_int,
        ctypes.c_int,
    ]
    lib.modbus_set_slave.argtypes = [ctypes.c_void_p, ctypes.c_int]
    lib.modbus_connect.argtypes = [ctypes.c_void_p]
    return lib
