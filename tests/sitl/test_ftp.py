"""MAVLink FTP as PX4 serves it: opcodes, sessions, bursts, CRC32 and NAKs on a server over a
fake link; then MAVSDK's ftp plugin and MAVProxy's parameter file decoder against the emulator."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from MAVProxy.modules.lib.param_ftp import ftp_param_decode
from mavsdk.asyncio.plugins import ftp as mavsdk_ftp
from pymavlink.dialects.v20 import common as mavlink

from sitl.ftp import (
    BURST_BYTES,
    MAX_DATA_BYTES,
    File,
    FileSystem,
    FtpError,
    FtpPayload,
    FtpServer,
    Opcode,
    px4_crc32,
    static_directory,
)
from sitl.params import ParamStore, int32_to_wire_float, pack_param_pck
from tests.sitl.helpers import Bench, FakeLink, roundtrip
from tests.sitl.mavsdk_helpers import api_config, emulated_drones

BIG = bytes(range(256)) * 400  # 102 400 bytes: three bursts
SMALL = b"hello, vehicle\n"


class Client:
    """Talks FTP to one :class:`FtpServer` over a fake link, numbering requests like a GCS."""

    def __init__(self, *, echo_session: bool = False, files: FileSystem | None = None) -> None:
        self.now_s = 0.0
        self.files = files or FileSystem(
            static_directory(
                {
                    "log": static_directory({"big.bin": File(lambda: BIG)}),
                    "small.txt": File(lambda: SMALL),
                }
            )
        )
        self.server = FtpServer(
            self.files, sysid=1, now_s=lambda: self.now_s, echo_session=echo_session
        )
        self.link = FakeLink()
        self.seq = 0

    def request(
        self,
        opcode: int,
        data: bytes = b"",
        *,
        session: int = 0,
        offset: int = 0,
        size: int | None = None,
        seq: int | None = None,
    ) -> list[FtpPayload]:
        """Send one request; the replies it caused."""
        seq = self.seq if seq is None else seq
        self.seq = seq + 1
        payload = FtpPayload(
            seq, session, opcode, len(data) if size is None else size, 0, 0, offset, data
        )
        msg = roundtrip(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, payload.pack()))
        self.link.clear()
        self.server.handle(msg, self.link)
        replies = self.link.of_type("FILE_TRANSFER_PROTOCOL")
        assert all((m.target_system, m.target_component) == (255, 190) for m in replies)
        return [FtpPayload.unpack(m.payload) for m in replies]

    def one(self, opcode: int, data: bytes = b"", **kwargs: int) -> FtpPayload:
        (reply,) = self.request(opcode, data, **kwargs)
        return reply

    def listing(self, path: str) -> list[bytes]:
        entries: list[bytes] = []
        while True:
            reply = self.one(Opcode.LIST_DIRECTORY, path.encode(), offset=len(entries))
            if reply.opcode == Opcode.NAK:
                assert reply.data[:1] == bytes([FtpError.EOF])
                return entries
            entries += [e for e in reply.data[: reply.size].split(b"\0") if e]


def nak(reply: FtpPayload, error: FtpError, request: Opcode) -> None:
    assert (reply.opcode, reply.req_opcode, reply.size, reply.data[:1]) == (
        Opcode.NAK,
        request,
        1,
        bytes([error]),
    )


# ------------------------------------------------------------------ the protocol
def test_list_directories_with_file_sizes_then_eof() -> None:
    client = Client()
    assert client.listing("/") == [b"Dlog", b"Fsmall.txt\t15"]
    assert client.listing("") == client.listing("/")
    assert client.listing("log") == [f"Fbig.bin\t{len(BIG)}".encode()]
    nak(
        client.one(Opcode.LIST_DIRECTORY, b"nowhere"),
        FtpError.FILE_NOT_FOUND,
        Opcode.LIST_DIRECTORY,
    )


def test_open_read_terminate_with_px4s_single_session_0() -> None:
    client = Client()
    opened = client.one(Opcode.OPEN_FILE_RO, b"/small.txt", session=7)
    assert (opened.opcode, opened.session, opened.size) == (Opcode.ACK, 0, 4)
    assert struct.unpack("<I", opened.data[:4]) == (len(SMALL),)
    assert opened.seq_number == 1  # request + 1
    read = client.one(Opcode.READ_FILE, session=0, offset=7, size=100)
    assert read.data[: read.size] == SMALL[7:]
    nak(client.one(Opcode.READ_FILE, session=0, offset=15, size=10), FtpError.EOF, Opcode.READ_FILE)
    nak(
        client.one(Opcode.READ_FILE, session=3, size=10), FtpError.INVALID_SESSION, Opcode.READ_FILE
    )
    # One session at a time, as PX4.
    nak(
        client.one(Opcode.OPEN_FILE_RO, b"log/big.bin"),
        FtpError.NO_SESSIONS_AVAILABLE,
        Opcode.OPEN_FILE_RO,
    )
    assert client.one(Opcode.TERMINATE_SESSION, session=0).opcode == Opcode.ACK
    nak(
        client.one(Opcode.TERMINATE_SESSION, session=0),
        FtpError.INVALID_SESSION,
        Opcode.TERMINATE_SESSION,
    )
    nak(client.one(Opcode.OPEN_FILE_RO, b"/missing"), FtpError.FILE_NOT_FOUND, Opcode.OPEN_FILE_RO)


def test_ardupilots_session_numbers_when_asked_for() -> None:
    client = Client(echo_session=True)
    assert client.one(Opcode.OPEN_FILE_RO, b"small.txt", session=171).session == 171
    assert client.one(Opcode.READ_FILE, session=171, size=5).data[:5] == b"hello"
    nak(client.one(Opcode.READ_FILE, session=0, size=5), FtpError.INVALID_SESSION, Opcode.READ_FILE)


def test_burst_read_streams_35_kb_bursts_and_ends_with_a_nak_eof() -> None:
    client = Client()
    client.one(Opcode.OPEN_FILE_RO, b"log/big.bin")
    received = bytearray()
    bursts = 0
    request_seq = 10
    while True:
        packets = client.request(
            Opcode.BURST_READ_FILE,
            session=0,
            offset=len(received),
            size=MAX_DATA_BYTES,
            seq=request_seq,
        )
        bursts += 1
        # Numbered on from the request, as PX4's stream numbers them.
        assert [p.seq_number for p in packets] == list(
            range(request_seq + 1, request_seq + 1 + len(packets))
        )
        request_seq = packets[-1].seq_number + 1
        data = [p for p in packets if p.opcode == Opcode.ACK]
        for packet in data:
            assert packet.offset == len(received) and packet.req_opcode == Opcode.BURST_READ_FILE
            received += packet.data[: packet.size]
        if packets[-1].opcode == Opcode.NAK:
            nak(packets[-1], FtpError.EOF, Opcode.BURST_READ_FILE)
            assert packets[-1].offset == len(BIG)
            break
        assert packets[-1].burst_complete == 1
        assert BURST_BYTES < sum(p.size for p in data) <= BURST_BYTES + MAX_DATA_BYTES
    assert bytes(received) == BIG and bursts == 3


def test_crc32_is_px4s_and_the_rest_is_naked_as_px4_does() -> None:
    client = Client()
    crc = client.one(Opcode.CALC_FILE_CRC32, b"log/big.bin")
    assert struct.unpack("<I", crc.data[:4]) == (px4_crc32(BIG),)
    for opcode in (Opcode.CREATE_FILE, Opcode.REMOVE_FILE, Opcode.RENAME, Opcode.WRITE_FILE):
        nak(client.one(opcode, b"log/big.bin"), FtpError.FILE_PROTECTED, opcode)
    nak(client.one(99), FtpError.UNKNOWN_COMMAND, 99)  # type: ignore[arg-type]
    nak(client.one(Opcode.READ_FILE, size=240), FtpError.INVALID_DATA_SIZE, Opcode.READ_FILE)
    assert client.one(Opcode.NONE).opcode == Opcode.ACK
    assert client.one(Opcode.RESET_SESSIONS).opcode == Opcode.ACK


def test_px4_crc32_has_no_inversions() -> None:
    def bitwise(data: bytes) -> int:  # CRC-32 polynomial, reflected, init 0, no final xor
        crc = 0
        for byte in data:
            crc ^= byte
            for _ in range(8):
                crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
        return crc

    for data in (b"", b"123456789", BIG[:1000]):
        assert px4_crc32(data) == bitwise(data)
    assert px4_crc32(BIG[500:], px4_crc32(BIG[:500])) == px4_crc32(BIG)  # crc32part chains


def test_a_repeated_request_gets_the_same_reply_without_doing_it_again() -> None:
    client = Client()
    client.one(Opcode.OPEN_FILE_RO, b"small.txt")
    first = client.one(Opcode.TERMINATE_SESSION, seq=40)
    again = client.one(Opcode.TERMINATE_SESSION, seq=40)  # the ACK got lost
    assert again == first and again.opcode == Opcode.ACK  # not INVALID_SESSION


def test_an_idle_session_closes_after_ten_seconds() -> None:
    client = Client()
    client.one(Opcode.OPEN_FILE_RO, b"small.txt")
    client.now_s = 10.5
    assert client.one(Opcode.OPEN_FILE_RO, b"log/big.bin").opcode == Opcode.ACK


def test_requests_for_other_systems_are_ignored() -> None:
    client = Client()
    msg = roundtrip(
        mavlink.MAVLink_file_transfer_protocol_message(
            0, 2, 1, FtpPayload(0, 0, Opcode.NONE, 0).pack()
        )
    )
    client.server.handle(msg, client.link)
    assert client.link.sent == []


# ------------------------------------------------------------------ the vehicle's files
def test_param_pck_only_with_ardupilots_extensions_and_mavproxy_decodes_it() -> None:
    bench = Bench()
    bench.deliver(
        mavlink.MAVLink_file_transfer_protocol_message(
            0, 1, 1, FtpPayload(0, 0, Opcode.OPEN_FILE_RO, 16, data=b"@PARAM/param.pck").pack()
        )
    )
    reply = FtpPayload.unpack(bench.link.of_type("FILE_TRANSFER_PROTOCOL")[-1].payload)
    nak(reply, FtpError.FILE_NOT_FOUND, Opcode.OPEN_FILE_RO)  # as on PX4

    store = ParamStore({"NAV_DLL_ACT": 2, "MIS_TAKEOFF_ALT": 4.5})
    decoded = ftp_param_decode(pack_param_pck(store))
    assert decoded is not None and decoded.defaults is None
    values = {name.decode(): value for name, value, _ in decoded.params}
    assert list(values) == list(store)
    assert values["NAV_DLL_ACT"] == 2 and values["CAL_ACC0_ID"] == 1310988
    assert values["MIS_TAKEOFF_ALT"] == pytest.approx(4.5)
    with_defaults = ftp_param_decode(pack_param_pck(store, with_defaults=True))
    assert with_defaults is not None and with_defaults.defaults is not None
    defaults = {name.decode(): value for name, value, _ in with_defaults.defaults}
    assert defaults["NAV_DLL_ACT"] == 0 and defaults["MIS_TAKEOFF_ALT"] == pytest.approx(2.5)


# ------------------------------------------------------------------ MAVSDK
@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_lists_downloads_and_compares_like_with_px4(tmp_path: Path) -> None:
    config = api_config(ftp={"ardupilot_extensions": True})
    async with emulated_drones(config) as (emulator, drones):
        ftp = mavsdk_ftp.FtpAsync(drones[0].system)
        listing = await ftp.list_directory("/")
        assert [(e.name, e.entry_type.name) for e in listing.entries] == [("log", "DIRECTORY")]
        params = emulator.autopilot(0).params
        await drones[0].param.set_param_int("NAV_DLL_ACT", 3)
        expected = pack_param_pck(params)
        for use_burst in (True, False):
            target = tmp_path / ("burst" if use_burst else "read")
            target.mkdir()  # MAVSDK's burst download does not create it
            async for result, progress in ftp.download("@PARAM/param.pck", str(target), use_burst):
                if result == mavsdk_ftp.FtpResult.NEXT:
                    assert progress.total_bytes == len(expected)
            assert (target / "param.pck").read_bytes() == expected
        assert await ftp.are_files_identical(str(target / "param.pck"), "@PARAM/param.pck")
        with pytest.raises(mavsdk_ftp.FtpError) as refused:
            async for _ in ftp.upload(str(target / "param.pck"), "/log"):
                pass
        assert refused.value.result == mavsdk_ftp.FtpResult.FILE_PROTECTED
        with pytest.raises(mavsdk_ftp.FtpError) as missing:
            async for _ in ftp.download("/log/none.ulg", str(tmp_path), True):
                pass
        assert missing.value.result == mavsdk_ftp.FtpResult.FILE_DOES_NOT_EXIST
    decoded = ftp_param_decode((target / "param.pck").read_bytes())
    assert decoded is not None
    assert {n.decode(): v for n, v, _ in decoded.params}["NAV_DLL_ACT"] == 3
    assert int32_to_wire_float(3) != 3  # the download carried the integer, not its float bytes
