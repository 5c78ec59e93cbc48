"""TMF8828 protocol, emulator and driver: bootloader, download, reassembly, bus clock, faults, rigs."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pytest

from tofjax.config import ConfigError
from tofjax.errors import UserError
from tofjax.hw import protocol as P
from tofjax.hw.bus import BusFaults, SimBus, SimClock, SimPin
from tofjax.hw.driver import DeviceError, DriverOptions, TMF8828
from tofjax.hw.emulator import DeviceFaults, EmulatorTiming, TMF8828Emulator, default_zone_map
from tofjax.hw.rig import Rig, RigSensor, emulated_bus, load_rig, load_rig_or_scene, open_array, rig_for_scene

ROOT = Path(__file__).resolve().parents[1]


def _signals(n_sensors, zones, seed=0, scale=3e5):
    """Synthetic expected counts spanning all three byte planes of the 24-bit bins."""
    rng = np.random.default_rng(seed)
    lam = rng.uniform(0, 1, (n_sensors, zones, P.N_BINS)) ** 4 * scale
    ref = rng.uniform(0, 1, (n_sensors, P.N_BINS)) ** 4 * scale
    return lam, ref


def _scene(optoskin, n_sensors=2, zones=7):
    return optoskin.replace(sensors=optoskin.sensors[:n_sensors],
                            sensor=optoskin.sensor.__class__(**{**optoskin.sensor.__dict__, "zones": zones}))


def _one_device(freq=400_000, **kw):
    clock = SimClock()
    bus = SimBus(freq, clock=clock)
    lam, ref = _signals(1, 7)
    emu = TMF8828Emulator(lam[0], ref[0], clock, noise=False, **kw)
    bus.attach(emu)
    pin = SimPin(emu)
    pin.on()
    return bus, emu


# ---- bootloader --------------------------------------------------------------------------------
def test_bootloader_checksum_and_frames():
    assert P.bl_checksum(bytes([0x14, 0x01, 0x29])) == (~(0x14 + 0x01 + 0x29)) & 0xFF == 0xC1
    assert P.bl_frame(0x14, b"\x29") == bytes([0x14, 0x01, 0x29, 0xC1])
    assert P.bl_frame(P.BL_RAMREMAP_RESET) == bytes([0x11, 0x00, 0xEE])
    with pytest.raises(ValueError):
        P.bl_frame(P.BL_W_RAM, bytes(129))


def test_bootloader_status_bytes():
    bus, emu = _one_device(timing=EmulatorTiming(bl_command_s=0.5e-3))  # slow enough to read 'busy'
    dev = TMF8828(bus)
    dev.power_up()
    assert bus.read_byte_data(P.ADDRESS, P.ENABLE) == 0x41  # cpu_ready | PON
    assert dev.app_id() == P.APPID_BOOTLOADER

    def send(frame):
        dev.write_block(P.BL_CMD_STAT, frame)
        busy = dev.read_block(P.BL_CMD_STAT, 3)
        bus.clock.sleep(1e-3)
        return busy, dev.read_block(P.BL_CMD_STAT, 3)

    busy, st = send(P.bl_frame(P.BL_DOWNLOAD_INIT, b"\x29"))
    assert busy[0] >= P.BL_BUSY_MIN and st == P.BL_OK == bytes([0, 0, 0xFF])
    bad = bytearray(P.bl_frame(P.BL_ADDR_RAM, b"\x00\x00"))
    bad[-1] ^= 0xFF
    assert send(bytes(bad))[1][0] == P.BL_CSUM_ERROR
    short = bytearray(P.bl_frame(P.BL_ADDR_RAM, b"\x00\x00"))
    short[1] = 5  # length field does not match
    assert send(bytes(short))[1][0] == P.BL_SIZE_ERROR
    assert send(P.bl_frame(P.BL_ADDR_RAM, b"\x00\x00"))[1] == P.BL_OK


# ---- images -----------------------------------------------------------------------------------
def test_intel_hex_roundtrip_and_errors(tmp_path):
    img = P.synthetic_image()
    assert len(img) == 7168 and img.startswith(P.SYNTHETIC_MAGIC)
    text = P.to_intel_hex(img)
    assert P.parse_intel_hex(text) == (P.RAM_BASE, img)
    hexfile = tmp_path / "app.hex"
    hexfile.write_text(text)
    binfile = tmp_path / "app.bin"
    binfile.write_bytes(img)
    assert P.load_image(hexfile) == img == P.load_image(binfile)
    lines = text.splitlines()
    broken = lines.copy()
    broken[3] = broken[3][:-2] + ("00" if broken[3][-2:] != "00" else "01")
    with pytest.raises(P.ImageError, match="checksum"):
        P.parse_intel_hex("\n".join(broken))
    with pytest.raises(P.ImageError, match="contiguous"):
        P.parse_intel_hex("\n".join(lines[:3] + lines[4:]))
    with pytest.raises(P.ImageError, match="end-of-file"):
        P.parse_intel_hex("\n".join(lines[:-1]))
    (tmp_path / "low.hex").write_text(P.to_intel_hex(img, start=0))
    with pytest.raises(P.ImageError, match="0x00200000"):
        P.load_image(tmp_path / "low.hex")
    with pytest.raises(UserError, match="not shipped"):
        P.load_image(tmp_path / "missing.hex")


def test_download_synthetic_image_starts_the_application():
    bus, emu = _one_device()
    dev = TMF8828(bus)
    dev.power_up()
    img = P.synthetic_image()
    t0, bytes0 = bus.clock.now(), bus.stats.bytes
    dev.download(img)
    assert dev.app_id() == P.APPID_APP
    assert bytes(emu.ram[: len(img)]) == img
    # one bootloader frame per 128-byte chunk, each one I2C write of reg + 3 + payload bytes
    assert bus.stats.bytes - bytes0 > len(img) + 4 * (len(img) // 128)
    assert bus.clock.now() - t0 > len(img) * 9 / 400_000
    assert dev.errors.total() == 0


def test_download_of_a_wrong_image_is_a_clear_error():
    bus, emu = _one_device()
    dev = TMF8828(bus)
    dev.power_up()
    with pytest.raises(DeviceError, match="did not start the application"):
        dev.download(P.synthetic_image(seed=1))
    assert dev.app_id() == P.APPID_BOOTLOADER


# ---- layouts and reassembly -------------------------------------------------------------------
@pytest.mark.parametrize("name", P.LAYOUTS)
def test_layout_covers_each_zone_once(name):
    lay = P.Layout(name)
    idx = [lay.zone_index(*s) for s in lay.slots()]
    assert len(idx) == len(set(idx)) == lay.n_zones
    if lay.is_8x8:
        assert sorted(idx) == list(range(64))
        assert lay.packets_per_subcapture * lay.n_subcaptures == 240  # the page's 240 packets + 4 results


@pytest.mark.parametrize("layout,zones", [("3x3", 7), ("3x3", 9), ("4x4", 16), ("3x6", 18), ("8x8", 64)])
def test_frame_reassembly_equals_emulated_histograms(optoskin, layout, zones):
    scene = _scene(optoskin, 1, zones)
    rig = Rig(scene="optoskin", sensors=(RigSensor(),), select="none", layout=layout, period_ms=2)
    lam, ref = _signals(1, zones, seed=zones)
    bus, _, emus = emulated_bus(rig, scene, noise=False, signals=(lam, ref), frequency_hz=1e6)
    arr = open_array(rig, scene, bus, None, P.synthetic_image()).open()
    for _ in range(2):
        f = arr.read_frame()
        z, r = emus[0].last_frame
        np.testing.assert_array_equal(f.histograms[0], z)
        np.testing.assert_array_equal(f.histograms[0], np.rint(lam[0]))
        np.testing.assert_array_equal(f.reference[0], np.rint(ref[0]))
        assert len(f.results[0]) == P.Layout(layout).n_subcaptures
    assert arr.errors.total() == 0


def test_emulated_rig_reproduces_the_forward_model(optoskin):
    """An emulated rig (noise off) gives `tofjax simulate`'s expected counts, rounded to whole counts."""
    from tofjax.scene import Touch
    from tofjax.simulate import expected_counts

    # the scene of tests/test_hw_record.py (its model is computed once per session)
    scene = optoskin.replace(sensors=optoskin.sensors[:2], name="optoskin-2",
                             touches=(Touch(position_m=(0.10, 0.20), radius_m=0.01, strength=1.0),))
    rig = rig_for_scene("optoskin", scene)
    bus, _, emus = emulated_bus(rig, scene, noise=False, frequency_hz=1e6)
    f = open_array(rig, scene, bus, None, P.synthetic_image()).open().read_frame()
    lam = expected_counts(scene)
    assert np.max(np.abs(f.histograms - lam)) <= 0.5 + 1e-9
    assert f.reference.shape == (2, 128) and 14 <= int(np.argmax(f.reference[0])) <= 16  # reference peak near bin 15
    # with noise: Poisson scatter around the model
    bus, _, _ = emulated_bus(rig, scene, noise=True, frequency_hz=1e6, signals=(lam, f.reference))
    fn = open_array(rig, scene, bus, None, P.synthetic_image()).open().read_frame()
    assert not np.array_equal(fn.histograms, f.histograms)
    z = (fn.histograms - lam) / np.sqrt(np.maximum(lam, 1))
    assert abs(z.mean()) < 0.1 and 0.8 < z.std() < 1.2


# ---- bus --------------------------------------------------------------------------------------
@pytest.mark.parametrize("freq", [100_000, 400_000, 1_000_000])
def test_bus_clock_counts_bits(freq):
    bus, emu = _one_device(freq)
    t0 = bus.clock.now()
    TMF8828(bus).read_block(P.CID_RID, P.HIST_PACKET_LEN)
    bits = 1 + (9 + 9 + 1) + (9 + 9 * P.HIST_PACKET_LEN + 1)  # start, addr+reg, rep. start, addr+data, stop
    assert bus.clock.now() - t0 == pytest.approx(bits / freq)
    with pytest.raises(ValueError):
        bus.read_i2c_block_data(P.ADDRESS, P.CID_RID, 33)  # smbus2's 32-byte limit


def test_frame_cost_scales_with_bus_speed(optoskin):
    scene = _scene(optoskin, 1, 7)
    rig = Rig(scene="optoskin", sensors=(RigSensor(),), select="none", period_ms=1)
    sig = _signals(1, 7)
    cost = {}
    for f in (100_000, 400_000, 1_000_000):
        bus, _, _ = emulated_bus(rig, scene, noise=False, signals=sig, frequency_hz=f)
        arr = open_array(rig, scene, bus, None, P.synthetic_image()).open()
        arr.read_frame()
        t0 = bus.clock.now()
        for _ in range(3):
            arr.read_frame()
        cost[f] = (bus.clock.now() - t0) / 3
    # 31 records of ~135 bytes: ~38 kbit per frame; bus-bound at every speed with a 1 ms period
    assert cost[100_000] == pytest.approx(4 * cost[400_000], rel=0.05)
    assert cost[400_000] == pytest.approx(2.5 * cost[1_000_000], rel=0.1)
    assert 0.035 < cost[1_000_000] < 0.05


def test_two_enabled_devices_at_one_address_collide():
    clock = SimClock()
    bus = SimBus(clock=clock)
    a = TMF8828Emulator(np.zeros((7, 128)), np.zeros(128), clock)
    b = TMF8828Emulator(np.zeros((7, 128)), np.zeros(128), clock)
    bus.attach(a), bus.attach(b)
    with pytest.raises(OSError) as e:
        bus.read_byte_data(P.ADDRESS, P.APPID)
    assert e.value.errno == errno.EREMOTEIO
    SimPin(a).on(), SimPin(b).on()
    a.regs[5], b.regs[5] = 0b1100, 0b1010
    assert bus.read_byte_data(P.ADDRESS, 5) == 0b1000  # open drain: wired AND


# ---- faults -----------------------------------------------------------------------------------
FAULTS = [
    ("nack", BusFaults(nack=0.05, seed=3), DeviceFaults(), "i2c"),
    ("timeout", BusFaults(timeout=0.03, seed=3), DeviceFaults(), "timeout"),
    ("corrupt", BusFaults(corrupt=0.1, seed=3), DeviceFaults(), "corrupt"),
    ("repeat", BusFaults(), DeviceFaults(repeat=0.05, seed=3), "repeat"),
    ("skip", BusFaults(), DeviceFaults(skip=0.02, seed=3), "skip"),
    ("wrong_cid", BusFaults(), DeviceFaults(wrong_cid=0.05, seed=3), "wrong_cid"),
    ("reset", BusFaults(), DeviceFaults(reset=0.01, seed=3), "reset"),
]


@pytest.mark.parametrize("select", ["mux", "pins"])
@pytest.mark.parametrize("name,bus_faults,device_faults,kind", FAULTS, ids=[f[0] for f in FAULTS])
def test_faults_are_counted_and_never_give_a_broken_frame(optoskin, select, name, bus_faults, device_faults, kind):
    scene = _scene(optoskin, 2, 7)
    if select == "mux":
        rig = rig_for_scene("optoskin", scene)
    else:
        rig = Rig(scene="optoskin", sensors=(RigSensor(enable_pin=17), RigSensor(enable_pin=27)), select="pins")
    sig = _signals(2, 7)
    bus, pins, emus = emulated_bus(rig, scene, noise=False, signals=sig, frequency_hz=1e6,
                                   bus_faults=bus_faults, device_faults=device_faults)
    arr = open_array(rig, scene, bus, pins, P.synthetic_image()).open()
    from tofjax.hw.driver import FrameDropped

    whole = 0
    for _ in range(12):
        try:
            f = arr.read_frame()
        except FrameDropped:
            continue
        whole += 1
        np.testing.assert_array_equal(f.histograms, np.rint(sig[0]))
        np.testing.assert_array_equal(f.reference, np.rint(sig[1]))
    assert whole >= 10
    assert arr.errors[kind] > 0
    if name == "reset":
        assert arr.errors["reset"] == sum(e.counts["resets"] for e in emus)


def test_one_reset_mid_frame_is_recovered(optoskin):
    scene = _scene(optoskin, 2, 7)
    rig = Rig(scene="optoskin", sensors=(RigSensor(enable_pin=17), RigSensor(enable_pin=27)), select="pins")
    sig = _signals(2, 7)
    bus, pins, emus = emulated_bus(rig, scene, noise=False, signals=sig, frequency_hz=1e6)
    arr = open_array(rig, scene, bus, pins, P.synthetic_image()).open()
    arr.read_frame()
    emus[1].armed.append("reset")
    f = arr.read_frame()
    np.testing.assert_array_equal(f.histograms, np.rint(sig[0]))
    assert arr.errors["reset"] == 1 and emus[1].counts["resets"] == 1
    assert emus[1].address == 0x43 and emus[1].app  # re-downloaded and moved back to its address


def test_a_dead_sensor_is_a_clear_error(optoskin):
    scene = _scene(optoskin, 1, 7)
    rig = Rig(scene="optoskin", sensors=(RigSensor(),), select="none")
    bus, _, emus = emulated_bus(rig, scene, noise=False, signals=_signals(1, 7), frequency_hz=1e6)
    emus[0].set_enable(False)
    with pytest.raises(UserError):
        open_array(rig, scene, bus, None, P.synthetic_image()).open()


# ---- rigs -------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", sorted((ROOT / "configs" / "rigs").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_rigs_load_and_emulate(path, optoskin):
    rig, scene, is_rig = load_rig_or_scene(str(path))
    assert is_rig and scene.n_sensors == len(rig.sensors)
    sig = _signals(scene.n_sensors, scene.sensor.zones)
    bus, pins, _ = emulated_bus(rig, scene, noise=False, signals=sig, frequency_hz=1e6)
    f = open_array(rig, scene, bus, pins, P.synthetic_image(), period_ms=2).open().read_frame()
    assert f.histograms.shape == scene.shape


def test_rig_errors(tmp_path):
    def rig(text):
        p = tmp_path / "rig.toml"
        p.write_text('scene = "optoskin"\n' + text)
        return load_rig(p)

    with pytest.raises(ConfigError, match="colour: unknown key"):
        rig('colour = "red"\n[[sensors]]\nenable_pin = 17\n')
    with pytest.raises(ConfigError, match="enable_pin: required"):
        rig('[[sensors]]\nenable_pin = 17\n[[sensors]]\nmux_channel = 1\n')
    with pytest.raises(ConfigError, match="mux_channel: must be in"):
        rig('select = "mux"\n[[sensors]]\nmux_channel = 9\n')
    with pytest.raises(ConfigError, match="GPIO is used twice"):
        rig('[[sensors]]\nenable_pin = 17\n[[sensors]]\nenable_pin = 17\n')
    p = tmp_path / "six.toml"
    p.write_text('scene = "optoskin"\nselect = "mux"\n[[sensors]]\nmux_channel = 0\n')
    with pytest.raises(ConfigError, match="1 sensors but its scene"):
        load_rig_or_scene(str(p))
    with pytest.raises(UserError, match="layout 3x3 has 9 zones"):
        P.layout_for(12, "3x3")


def test_default_zone_map():
    assert default_zone_map(P.Layout("3x3"), 7) == list(range(7))
    assert default_zone_map(P.Layout("4x4"), 10) == [0, 1, 2, 3, 4, 5, 6, 7, 9, 10]
    assert default_zone_map(P.Layout("8x8"), 3) == [0, 1, 2]


def test_driver_options_validate():
    with pytest.raises(UserError, match="8x8 mode needs SPAD map 15"):
        DriverOptions(layout="8x8", spad_map=1)
    with pytest.raises(UserError, match="period_ms"):
        DriverOptions(period_ms=0)
    assert EmulatorTiming().stop_s == 0.025


def test_bench_acquire_fast(optoskin):
    """The benchmark's measurement on a small case: bus-limited within 10 %, driver CPU well under the period."""
    from test_studies import load

    bench = load("bench_acquire")
    scene = _scene(optoskin, 1, 7)
    rig = Rig(scene="optoskin", sensors=(RigSensor(),), select="none", period_ms=1)
    r = bench.run_case("1x3x3", rig, scene, _signals(1, 7), 1_000_000, 3, 1)
    assert r["rate_vs_bus_limited"] >= 0.9 and r["driver_cpu_fraction"] < 0.5 and r["errors"] == 0
    # 31 records x (INT read + 135-byte read + clear): ~41 kbit, ~41 ms at 1 MHz
    assert 0.038 < r["bus_limited_period_s"] < 0.043


def test_reopening_a_running_rig_needs_no_download(optoskin):
    """A second session on sensors that kept power (mux rig, no enable lines): stop, configure, measure."""
    scene = _scene(optoskin, 2, 7)
    rig = rig_for_scene("optoskin", scene)
    sig = _signals(2, 7)
    bus, _, emus = emulated_bus(rig, scene, noise=False, signals=sig, frequency_hz=1e6)
    open_array(rig, scene, bus, None, P.synthetic_image()).open().read_frame()
    emus[0]._command(P.CMD_MEASURE)  # left measuring by a crashed session, command still pending
    b0 = bus.stats.bytes
    arr = open_array(rig, scene, bus, None, P.synthetic_image(seed=99)).open()  # would not boot if downloaded
    assert bus.stats.bytes - b0 < 1000
    np.testing.assert_array_equal(arr.read_frame().histograms, np.rint(sig[0]))


def test_int_pin_replaces_polling_over_the_bus(optoskin):
    """With the INT line wired, the driver waits on the pin: same frames, far fewer transfers while waiting."""
    from tofjax.hw.rig import emulated_int_pins

    scene = _scene(optoskin, 2, 7)
    sig = _signals(2, 7)
    transfers = {}
    for wired in (False, True):
        sensors = tuple(RigSensor(enable_pin=17 + i, int_pin=(20 + i) if wired else None) for i in range(2))
        rig = Rig(scene="optoskin", sensors=sensors, select="pins", period_ms=33)
        bus, pins, emus = emulated_bus(rig, scene, noise=False, signals=sig, frequency_hz=400_000)
        arr = open_array(rig, scene, bus, pins, P.synthetic_image(), int_pins=emulated_int_pins(rig, emus)).open()
        n0, t0 = bus.stats.transfers, bus.clock.now()
        for _ in range(2):
            np.testing.assert_array_equal(arr.read_frame().histograms, np.rint(sig[0]))
        transfers[wired] = (bus.stats.transfers - n0, bus.clock.now() - t0)
    assert transfers[True][0] < 0.8 * transfers[False][0]
    assert transfers[True][1] == pytest.approx(transfers[False][1], rel=0.05)
    with pytest.raises(ConfigError, match="GPIO is used twice"):
        Rig(scene="optoskin", sensors=(RigSensor(enable_pin=17, int_pin=17),))
