"""The CRC-32 that Unitree's G1 firmware checks on LowCmd (and sets on LowState), docs/environment.md §9.

The message is packed as the little-endian C struct (natural alignment: 1004 bytes for
LowCmd, 2092 for LowState; *not* the CDR wire bytes), read as 32-bit little-endian words, and
every word but the last (the ``crc`` field itself) is fed MSB first through CRC-32 with
polynomial 0x04C11DB7, initial value 0xFFFFFFFF and no final XOR.

Feeding each word MSB first is the non-reflected ("MPEG-2") CRC over the words' big-endian
bytes. That equals the reflected CRC of zlib run on bit-reversed bytes, bit-reversed back, so
the whole computation stays in C (zlib, ``bytes.translate``): microseconds per message, which
matters for a 500 Hz LowState. ``crc32_reference`` is the plain bit loop, for tests.
"""

from __future__ import annotations

import re
import struct
import zlib

import numpy as np

from agents.deploy.messages import LOWSTATE_XCDR1, NUM_MOTORS, LowCmd_, LowState_, low_cmd_fields, low_state_fields

POLYNOMIAL = 0x04C11DB7
#: C-struct packing (docs/environment.md §9): header, 35 motor records, reserve + crc.
LOWCMD_FORMAT = "<2B2x" + "B3x5fI" * NUM_MOTORS + "5I"
LOWSTATE_FORMAT = "<2I2B2xI" + "13fh2x" + "B3x4f2hf7I" * NUM_MOTORS + "40B5I"
LOWCMD_PACKED_BYTES = struct.calcsize(LOWCMD_FORMAT)  # 1004
LOWSTATE_PACKED_BYTES = struct.calcsize(LOWSTATE_FORMAT)  # 2092

_BIT_REVERSED_BYTE = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def _reverse32(x: int) -> int:
    return int(f"{x:032b}"[::-1], 2)


def crc32_words(words: bytes) -> int:
    """CRC of little-endian 32-bit ``words`` (length a multiple of 4), each fed MSB first."""
    if len(words) % 4:
        raise ValueError(f"CRC input must be whole 32-bit words, got {len(words)} bytes")
    big_endian = np.frombuffer(words, dtype="<u4").astype(">u4").tobytes()
    reflected = zlib.crc32(big_endian.translate(_BIT_REVERSED_BYTE)) ^ 0xFFFFFFFF  # undo zlib's final XOR
    return _reverse32(reflected)


def crc32_reference(words: list[int]) -> int:
    """The bit-by-bit definition (slow; tests compare ``crc32_words`` with it)."""
    crc = 0xFFFFFFFF
    for word in words:
        for bit in range(31, -1, -1):
            top = (crc >> 31) ^ ((word >> bit) & 1)
            crc = (crc << 1) & 0xFFFFFFFF
            if top:
                crc ^= POLYNOMIAL
    return crc


def pack_low_cmd(msg: LowCmd_) -> bytes:
    """The 1004-byte C layout of a LowCmd_ (its ``crc`` field included, as the last word)."""
    return struct.pack(LOWCMD_FORMAT, *low_cmd_fields(msg))


def pack_low_state(msg: LowState_) -> bytes:
    """The 2092-byte C layout of a LowState_ (its ``crc`` field included, as the last word)."""
    return struct.pack(LOWSTATE_FORMAT, *low_state_fields(msg))


def _field_bytes(fmt: str) -> list[range]:
    """The byte ranges of each value a little-endian ``struct`` format packs (pads left out)."""
    out, offset = [], 0
    for count, code in re.findall(r"(\d*)([a-zA-Z])", fmt.lstrip("<")):
        n, size = int(count or 1), struct.calcsize("<" + code)
        if code == "x":
            offset += n
        elif code == "s":
            out.append(range(offset, offset + n))
            offset += n
        else:
            out += [range(offset + i * size, offset + (i + 1) * size) for i in range(n)]
            offset += n * size
    return out


def _cdr_to_c_index() -> np.ndarray:
    """For each byte of the C layout of a LowState (``LOWSTATE_FORMAT``) the byte of its XCDR1
    sample (``messages.LOWSTATE_XCDR1``, header included) that holds it; pads point one past
    the sample, where ``low_state_crc_ok_cdr`` puts a zero (``pack_low_state`` packs zeros)."""
    c, cdr = _field_bytes(LOWSTATE_FORMAT), _field_bytes(LOWSTATE_XCDR1.format)[1:]  # [1:]: the header
    index = np.full(LOWSTATE_PACKED_BYTES, LOWSTATE_XCDR1.size, dtype=np.intp)
    for dst, src in zip(c, cdr, strict=True):
        index[dst.start:dst.stop] = np.arange(src.start, src.stop)
    return index


_CDR_TO_C = _cdr_to_c_index()


def low_state_crc_ok_cdr(data: bytes) -> bool:
    """``crc_ok(LowState_.deserialize(data))`` from the XCDR1 little-endian bytes alone
    (``messages.is_low_state_xcdr1``): the C layout gathered from them in one NumPy step, then
    the same CRC. Equal on real and corrupted samples (``tests/agents/deploy/test_deploy_messages.py``)."""
    sample = np.frombuffer(data, np.uint8, count=LOWSTATE_XCDR1.size)
    packed = np.append(sample, np.uint8(0))[_CDR_TO_C].tobytes()
    return int.from_bytes(packed[-4:], "little") == crc32_words(packed[:-4])


def low_cmd_crc(msg: LowCmd_) -> int:
    return crc32_words(pack_low_cmd(msg)[:-4])


def low_state_crc(msg: LowState_) -> int:
    return crc32_words(pack_low_state(msg)[:-4])


def with_crc(msg: LowCmd_ | LowState_) -> LowCmd_ | LowState_:
    """Set ``msg.crc`` in place (and return ``msg``)."""
    msg.crc = low_cmd_crc(msg) if isinstance(msg, LowCmd_) else low_state_crc(msg)
    return msg


def crc_ok(msg: LowCmd_ | LowState_) -> bool:
    expected = low_cmd_crc(msg) if isinstance(msg, LowCmd_) else low_state_crc(msg)
    return int(msg.crc) == expected
