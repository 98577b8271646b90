"""What a device says of itself: read device identification (FC 43, MEI type 14) and
report server id (FC 17), built and parsed, pure.

The Modbus Application Protocol (V1.1b3, 6.21) numbers the objects: 0-2 are the basic
ones every implementing device must have, 3-6 regular, 0x80-0xFF the vendor's own
(extended). A reply that does not fit in one frame says "more follows" and the next
object's id, to be asked for in a further request.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping

from rtupoll.frozen import frozen

MEI_DEVICE_ID = 0x0E
# the standard's object ids and names (the profile key: the name in snake_case)
OBJECTS: Mapping[int, str] = {
    0: "VendorName", 1: "ProductCode", 2: "MajorMinorRevision", 3: "VendorUrl",
    4: "ProductName", 5: "ModelName", 6: "UserApplicationName",
}
OBJECT_KEYS: Mapping[str, int] = {
    "vendor_name": 0, "product_code": 1, "major_minor_revision": 2, "vendor_url": 3,
    "product_name": 4, "model_name": 5, "user_application_name": 6,
}
# read device id codes: what a request asks for
CODES: Mapping[str, int] = {"basic": 1, "regular": 2, "extended": 3, "one": 4}
CONFORMITY: Mapping[int, str] = {
    0x01: "basic, stream access", 0x02: "regular, stream access",
    0x03: "extended, stream access", 0x81: "basic, stream and individual access",
    0x82: "regular, stream and individual access",
    0x83: "extended, stream and individual access",
}
LAST_OBJECT = {1: 0x02, 2: 0x06, 3: 0xFF}  # the last object id each code covers


def object_name(obj: int) -> str:
    return OBJECTS.get(obj, f"private 0x{obj:02X}" if obj >= 0x80 else f"reserved 0x{obj:02X}")


def device_id_request(code: int = 1, first: int = 0) -> bytes:
    """The request PDU: read device id ``code`` (1 basic .. 4 one object) from ``first``."""
    return bytes((43, MEI_DEVICE_ID, code, first))


@frozen
class DeviceId:
    """One read device identification reply."""

    code: int
    conformity: int
    more: bool  # more objects follow: ask again from ``next_object``
    next_object: int
    objects: tuple[tuple[int, bytes], ...]


def parse_device_id(pdu: bytes) -> DeviceId:
    """A reply PDU (``2B 0E ...``) -> its objects; ValueError when it does not add up."""
    if len(pdu) < 7 or pdu[0] != 43 or pdu[1] != MEI_DEVICE_ID:
        raise ValueError("not a read device identification reply")
    code, conformity, more, next_object, count = pdu[2:7]
    objects: list[tuple[int, bytes]] = []
    i = 7
    for _ in range(count):
        if i + 2 > len(pdu):
            raise ValueError(f"{count} objects announced, the reply ends after {len(objects)}")
        obj, size = pdu[i], pdu[i + 1]
        if i + 2 + size > len(pdu):
            raise ValueError(f"object 0x{obj:02X} announces {size} bytes, "
                             f"{len(pdu) - i - 2} follow")
        objects.append((obj, pdu[i + 2 : i + 2 + size]))
        i += 2 + size
    if i != len(pdu):
        raise ValueError(f"{len(pdu) - i} byte(s) after the last object")
    if more not in (0x00, 0xFF):
        raise ValueError(f"'more follows' is 0x{more:02X} (the standard: 00 or FF)")
    return DeviceId(code, conformity, more == 0xFF, next_object, tuple(objects))


def device_id_reply(code: int, first: int, objects: Mapping[int, bytes],
                    conformity: int = 0x83) -> bytes:
    """The reply PDU a device gives to ``device_id_request(code, first)`` (a simulator's),
    split with "more follows" when the objects do not fit one frame; ValueError for an
    object the device does not have (code 4) or a code it does not know."""
    if code == 4:
        if first not in objects:
            raise ValueError(f"no object 0x{first:02X}")
        chosen = [first]
    elif code in LAST_OBJECT:
        chosen = [o for o in sorted(objects) if first <= o <= LAST_OBJECT[code]]
        if first not in objects:
            chosen = [o for o in sorted(objects) if o <= LAST_OBJECT[code]]  # from the start
    else:
        raise ValueError(f"read device id code {code}")
    body, count, more, following = b"", 0, 0x00, 0x00
    for obj in chosen:
        item = bytes((obj, len(objects[obj]))) + objects[obj]
        if 7 + len(body) + len(item) > 253 - 3:  # the PDU within one RTU frame
            more, following = 0xFF, obj
            break
        body += item
        count += 1
    return struct.pack(">BBBBBBB", 43, MEI_DEVICE_ID, code, conformity, more, following,
                       count) + body


@frozen
class ServerId:
    """A report server id reply: the device's own bytes, the run indicator where it is
    where the standard puts it (after a one-byte id), and what follows."""

    data: bytes

    @property
    def server_id(self) -> bytes:
        return self.data[:1]

    @property
    def running(self) -> bool | None:
        """ON/OFF when the byte after the id is 0xFF/0x00; None when it is neither (the id
        is longer: the standard leaves its length to the device)."""
        if len(self.data) < 2 or self.data[1] not in (0x00, 0xFF):
            return None
        return self.data[1] == 0xFF

    @property
    def additional(self) -> bytes:
        return self.data[2:] if self.running is not None else self.data[1:]


def parse_server_id(pdu: bytes) -> ServerId:
    if len(pdu) < 2 or pdu[0] != 17 or pdu[1] != len(pdu) - 2:
        raise ValueError("not a report server id reply (byte count and length disagree)")
    return ServerId(pdu[2:])


def server_id_reply(server_id: bytes, running: bool = True, additional: bytes = b"") -> bytes:
    data = server_id + bytes((0xFF if running else 0x00,)) + additional
    return bytes((17, len(data))) + data
