"""CDR (XCDR1, little endian) codec for the loop's hot messages, straight between the
node's dicts and the bytes DDS carries.

Why not the message classes: per batch the plant and the controller each built one rclpy
message from a dict and turned one back into a dict. Construction, per-field setters and
the C conversion cost ~25-35 us per message on this machine, a tenth of the lockstep
graph's whole batch; rclpy publishes and takes serialized bytes just as well
(``Publisher.publish(bytes)``, ``create_subscription(..., raw=True)``). rosbags' CDR code
works on its own dataclasses, so the dict would still be copied into one.

A codec is compiled once per message type from the type's own field list
(``get_fields_and_field_types()``): primitives, strings, fixed arrays and sequences of
primitives, and the std_msgs/Header (builtin_interfaces/Time + frame_id). Consecutive
fixed-size fields form a run packed by one ``struct.Struct``; a run's padding depends on
where it starts, so each run has one Struct per start offset modulo 8. Pad bytes are
zero, so the same values give the same bytes (rclpy leaves them as they were in memory).
Decoding checks every length against the buffer: a short or inconsistent message raises
``CdrError``, never reads past its end.
"""
from __future__ import annotations

import struct

import numpy as np

HEADER = b"\x00\x01\x00\x00"        # CDR_LE encapsulation, no options

_PRIMITIVES = {  # rosidl name -> (struct code, size, numpy dtype)
    "boolean": ("?", 1, np.bool_), "octet": ("B", 1, np.uint8), "char": ("B", 1, np.uint8),
    "uint8": ("B", 1, np.uint8), "int8": ("b", 1, np.int8), "uint16": ("H", 2, np.uint16),
    "int16": ("h", 2, np.int16), "uint32": ("I", 4, np.uint32), "int32": ("i", 4, np.int32),
    "uint64": ("Q", 8, np.uint64), "int64": ("q", 8, np.int64), "float": ("f", 4, np.float32),
    "double": ("d", 8, np.float64),
}
MAX_STRING_BYTES = 1 << 20            # hostile lengths are refused, not allocated
# the lengths of strings and sequences, packed by one compiled Struct (struct.pack_into('<I', ...)
# looked the format up in struct's cache at each of a message's ~6 lengths)
_U32 = struct.Struct("<I")


class CdrError(ValueError):
    """A buffer that is not a valid serialization of the expected type."""


def _run_structs(items: list[tuple[str, int, int]]) -> list[struct.Struct]:
    """One Struct per start offset mod 8 for a run of (code, size, count) fields."""
    out = []
    for start in range(8):
        fmt = ["<"]
        pos = start
        for code, size, count in items:
            pad = (-pos) % size
            if pad:
                fmt.append(f"{pad}x")
            fmt.append(f"{count}{code}" if count > 1 else code)
            pos += pad + size * count
        out.append(struct.Struct("".join(fmt)))
    return out


def _fields(cls) -> list[tuple[str, str]]:
    out = []
    for name, ftype in cls.get_fields_and_field_types().items():
        if ftype == "std_msgs/Header":
            out += [(f"{name}.sec", "int32"), (f"{name}.nanosec", "uint32"), (f"{name}.frame_id", "string")]
        else:
            out.append((name, ftype))
    return out


class Codec:
    """dict <-> CDR bytes for one message class (see the module docstring).

    ``encode(values, sec, nanosec, frame_id)``: ``values`` holds the fields but the header;
    a missing one is zero / empty, as in a fresh message; fixed arrays and sequences take
    anything numpy converts. ``decode(raw)`` -> (sec, nanosec, frame_id, values); sequences
    and fixed arrays come back as numpy arrays (sequences: read-only views of ``raw``), the
    rest as Python scalars / str."""

    def __init__(self, cls):
        self.cls = cls
        self.name = cls.__name__
        pre, enc, dec = [], [], []          # encode: conversions first (they size the buffer)
        size_terms = []
        fixed_bytes = 0
        env: dict = {"np": np, "struct": struct, "CdrError": CdrError, "MAX": MAX_STRING_BYTES, "HEADER": HEADER,
                     "NAME": self.name, "PACK_U32": _U32.pack_into, "UNPACK_U32": _U32.unpack_from}
        run: list[tuple[str, str, int, int, bool]] = []       # (field, code, size, count, is_header)
        k = 0

        def flush_run():
            nonlocal k, fixed_bytes
            if not run:
                return
            structs = _run_structs([(c, s, n) for _, c, s, n, _ in run])
            fixed_bytes += max(st.size for st in structs)
            env[f"S{k}"] = [st.pack_into for st in structs]
            env[f"U{k}"] = [st.unpack_from for st in structs]
            env[f"Z{k}"] = [st.size for st in structs]
            args = []
            for field, code, _, count, is_header in run:
                if is_header:
                    args.append(field.replace(".", "_"))
                elif count > 1:
                    env[f"E_{field}"] = (False if code == "?" else 0,) * count
                    args.append(f"*v.get({field!r}, E_{field})")
                else:
                    args.append(f"v.get({field!r}, {False if code == '?' else 0})")
            enc.append(f"r = pos & 7; S{k}[r](mv, pos, {', '.join(args)}); pos += Z{k}[r]")
            dec.append(f"r = pos & 7; z = Z{k}[r]")
            dec.append("if pos + z > end: raise CdrError(f'{NAME}: truncated at byte {pos}')")
            dec.append(f"t = U{k}[r](raw, pos); pos += z")
            i = 0
            for field, code, _, count, is_header in run:
                if is_header:
                    dec.append(f"header_{field.split('.')[1]} = t[{i}]")
                elif count > 1:
                    env[f"A_{field}"] = _DTYPE_OF_CODE[code]
                    dec.append(f"v[{field!r}] = np.array(t[{i}:{i + count}], dtype=A_{field})")
                else:
                    dec.append(f"v[{field!r}] = t[{i}]")
                i += count
            run.clear()
            k += 1

        for field, ftype in _fields(cls):
            is_header = field.startswith("header.")
            if ftype in _PRIMITIVES:
                code, size, _ = _PRIMITIVES[ftype]
                run.append((field, code, size, 1, is_header))
                continue
            if "[" in ftype and ftype.endswith("]") and ftype.split("[", 1)[0] in _PRIMITIVES:
                code, size, _ = _PRIMITIVES[ftype.split("[", 1)[0]]
                run.append((field, code, size, int(ftype.split("[", 1)[1][:-1]), is_header))
                continue
            flush_run()
            if ftype == "string":
                src = "frame_id" if is_header else f"v.get({field!r}, '')"
                dst = "frame_id" if is_header else f"v[{field!r}]"
                pre.append(f"b{k} = {src}.encode()")
                size_terms.append(f"len(b{k})")
                fixed_bytes += 3 + 4 + 1
                enc.append(f"pos += (-pos) & 3; n = len(b{k}) + 1")
                enc.append(f"PACK_U32(mv, pos, n); pos += 4; mv[pos:pos + n - 1] = b{k}; pos += n")
                dec.append("pos += (-pos) & 3")
                dec.append("if pos + 4 > end: raise CdrError(f'{NAME}: truncated at byte {pos}')")
                dec.append("n = UNPACK_U32(raw, pos)[0]; pos += 4")
                dec.append(f"if n < 1 or n > MAX or pos + n > end: raise CdrError(f'{{NAME}}: bad string length {{n}} "
                           f"({field})')")
                # an empty string (the frame_id, mostly) is not sliced and decoded
                dec.append(f"{dst} = bytes(raw[pos:pos + n - 1]).decode('utf-8', 'replace') if n > 1 else ''; "
                           "pos += n")
            elif ftype.startswith("sequence<") and ftype[9:-1] in _PRIMITIVES:
                code, size, dtype = _PRIMITIVES[ftype[9:-1]]
                env[f"D{k}"] = np.dtype(dtype).newbyteorder("<")
                env[f"E{k}"] = np.zeros(0, env[f"D{k}"])
                env[f"R{k}"] = np.zeros(0, env[f"D{k}"])
                env[f"R{k}"].flags.writeable = False
                # a field not given is the empty sequence itself, not converted (the DriveCommand of
                # either machine leaves the other's three out)
                pre.append(f"a{k} = np.ascontiguousarray(v[{field!r}], dtype=D{k}).reshape(-1) if {field!r} in v "
                           f"else E{k}")
                size_terms.append(f"a{k}.nbytes")
                fixed_bytes += 3 + 4 + 7
                enc.append(f"pos += (-pos) & 3; n = a{k}.size; PACK_U32(mv, pos, n); pos += 4")
                if size > 1:
                    enc.append(f"pos += (-pos) & {size - 1} if n else 0")
                enc.append(f"mv[pos:pos + n * {size}] = a{k}.tobytes(); pos += n * {size}")
                dec.append("pos += (-pos) & 3")
                dec.append("if pos + 4 > end: raise CdrError(f'{NAME}: truncated at byte {pos}')")
                dec.append("n = UNPACK_U32(raw, pos)[0]; pos += 4")
                if size > 1:
                    dec.append(f"pos += (-pos) & {size - 1} if n else 0")
                dec.append(f"if pos + n * {size} > end: raise CdrError(f'{{NAME}}: {field} claims {{n}} elements "
                           f"past the end')")
                # an empty one is a shared read-only empty array, as a view of raw would be
                dec.append(f"v[{field!r}] = np.frombuffer(raw, D{k}, n, pos) if n else R{k}; pos += n * {size}")
            else:
                raise TypeError(f"{self.name}.{field}: {ftype} is not supported by bike_plant.cdr")
            k += 1
        flush_run()
        # generated straight-line code; positions count from after the 4-byte encapsulation
        src = ["def encode(v, header_sec, header_nanosec, frame_id):"]
        src += [f"    {line}" for line in pre]
        src.append(f"    buf = bytearray({4 + fixed_bytes}{''.join(' + ' + t for t in size_terms)})")
        src += ["    buf[:4] = HEADER", "    mv = memoryview(buf)[4:]", "    pos = 0"]
        src += [f"    {line}" for line in enc]
        src += ["    mv.release()", "    del buf[4 + pos:]", "    return bytes(buf)"]
        src += ["def decode(raw):", "    end = len(raw) - 4", "    raw = memoryview(raw)[4:]", "    pos = 0",
                "    v = {}", "    header_sec = header_nanosec = 0", "    frame_id = ''"]
        src += [f"    {line}" for line in dec]
        src.append("    return header_sec, header_nanosec, frame_id, v")
        exec("\n".join(src), env)  # noqa: S102 - our own generated code, from the message's field list
        self._encode = env["encode"]
        self._decode = env["decode"]

    def encode(self, values: dict, sec: int = 0, nanosec: int = 0, frame_id: str = "") -> bytes:
        """The serialized message (4-byte encapsulation header included)."""
        try:
            return self._encode(values, sec, nanosec, frame_id)
        except (struct.error, ValueError, TypeError, OverflowError) as exc:
            raise CdrError(f"{self.name}: cannot encode ({exc})") from None

    def decode(self, raw) -> tuple[int, int, str, dict]:
        """(header sec, nanosec, frame_id, fields) of a serialized message; CdrError if malformed."""
        if len(raw) < 4 or raw[0] != 0 or raw[1] != 1:
            raise CdrError(f"{self.name}: not a little-endian CDR buffer")
        try:
            return self._decode(raw)
        except CdrError:
            raise
        except (struct.error, ValueError, UnicodeDecodeError) as exc:
            raise CdrError(f"{self.name}: {exc}") from None


_DTYPE_OF_CODE = {code: dtype for code, _, dtype in _PRIMITIVES.values()}
