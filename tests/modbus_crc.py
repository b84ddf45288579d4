"""An independent CRC-16/MODBUS for the tests, written from the spec and not from pymodbus or labcal:
MODBUS over Serial Line Specification and Implementation Guide V1.02, §6.2.2 "CRC Generation".

1. Load a 16-bit register with FFFFh.
2. XOR the next 8-bit byte of the message with the low byte of the register.
3. Shift the register one bit right (towards the LSB), zero-filling the MSB; if the bit shifted
   out was 1, XOR the register with the polynomial A001h (0x8005 reflected).
4. Repeat 3 until 8 shifts are done; then 2-4 for every byte of the message.
5. The register is the CRC; it is appended low-order byte first.
"""

from __future__ import annotations

POLYNOMIAL = 0xA001


def crc16_modbus(message: bytes) -> int:
    register = 0xFFFF
    for byte in message:
        register ^= byte
        for _ in range(8):
            lsb = register & 1
            register >>= 1
            if lsb:
                register ^= POLYNOMIAL
    return register


def with_crc(message: bytes) -> bytes:
    """The frame on the wire: the message, then its CRC low byte first."""
    crc = crc16_modbus(message)
    return message + bytes([crc & 0xFF, crc >> 8])


def crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and with_crc(frame[:-2]) == frame
