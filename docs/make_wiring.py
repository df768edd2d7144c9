"""Draw the box's wiring (Raspberry Pi 5, two CSI cameras, MPU-6050 on I2C1) as an SVG.

The I2C bus and address come from ``firmware_cfg/device.toml`` (section ``[imu]``), so the
drawing shows what the device code opens.  Plain XML text, no drawing library.

    python docs/make_wiring.py [--out docs/img/wiring.svg]
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path
from xml.sax.saxutils import escape

ROOT = Path(__file__).resolve().parent.parent

# 40-pin header: the pins this box uses -> (signal on the Pi, MPU-6050 breakout pin, wire colour)
HEADER_WIRES = [
    (1, "3V3", "VCC", "#d32f2f"),
    (6, "GND", "GND", "#212121"),
    (5, "GPIO3 / SCL1", "SCL", "#f9a825"),
    (3, "GPIO2 / SDA1", "SDA", "#1976d2"),
]
# pin order of the common GY-521 breakout, top to bottom
MPU_PINS = ["VCC", "GND", "SCL", "SDA", "XDA", "XCL", "AD0", "INT"]

W, H = 1010, 760
BOARD_Y = 130                           # top edge of the Pi board
HDR_X, HDR_Y, PITCH = 90, 175, 20       # header pin 1 (inner row) and pitch
LANE_Y, LANE_STEP = 72, 14              # the wires' runs above the board
MPU_X, MPU_Y, MPU_STEP = 760, 215, 30   # first breakout pin


def imu_settings(device_toml: Path) -> tuple[int, int]:
    """The [imu] bus and address the device opens (defaults of the settings schema: 1, 0x68)."""
    data = tomllib.loads(device_toml.read_text(encoding="utf-8"))
    imu = data.get("imu", {})
    bus, address = int(imu.get("bus", 1)), int(imu.get("address", 0x68))
    if address not in (0x68, 0x69):
        raise SystemExit(f"{device_toml}: imu.address = {address:#x}, expected 0x68 or 0x69")
    return bus, address


def header_pin_xy(pin: int) -> tuple[float, float]:
    """Odd pins on the inner row, even pins on the board edge; pin 1 at the left end."""
    col = (pin - 1) // 2
    x = HDR_X + col * PITCH
    y = HDR_Y if pin % 2 else HDR_Y - PITCH
    return x, y


def mpu_pin_xy(name: str) -> tuple[float, float]:
    return MPU_X, MPU_Y + MPU_PINS.index(name) * MPU_STEP


def text(x: float, y: float, s: str, size: int = 13, anchor: str = "start", weight: str = "normal",
         fill: str = "#111") -> str:
    return (f'<text x="{x:.1f}" y="{y:.1f}" font-size="{size}" text-anchor="{anchor}" '
            f'font-weight="{weight}" fill="{fill}">{escape(s)}</text>')


def rect(x: float, y: float, w: float, h: float, fill: str, stroke: str = "#333", rx: float = 6,
         extra: str = "") -> str:
    return (f'<rect x="{x:.1f}" y="{y:.1f}" width="{w:.1f}" height="{h:.1f}" rx="{rx}" fill="{fill}" '
            f'stroke="{stroke}" stroke-width="1.5" {extra}/>')


def polyline(points: list[tuple[float, float]], colour: str, width: float = 3.0, extra: str = "") -> str:
    pts = " ".join(f"{x:.1f},{y:.1f}" for x, y in points)
    return (f'<polyline points="{pts}" fill="none" stroke="{colour}" stroke-width="{width}" '
            f'stroke-linejoin="round" stroke-linecap="round" {extra}/>')


def dot(x: float, y: float, colour: str, r: float = 4.5) -> str:
    return f'<circle cx="{x:.1f}" cy="{y:.1f}" r="{r}" fill="{colour}"/>'


def draw(bus: int, address: int) -> str:
    out: list[str] = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" '
        f'font-family="DejaVu Sans, Helvetica, Arial, sans-serif">',
        f'<rect width="{W}" height="{H}" fill="white"/>',
        text(W / 2, 30, "stereopath box: Raspberry Pi 5, two CSI cameras, MPU-6050 on I2C1", 18, "middle", "bold"),
        text(W / 2, 50, "schematic, not to scale; viewed from the component side", 12, "middle", fill="#555"),
    ]
    # the Pi 5 board
    bx, by, bw, bh = 40, BOARD_Y, 560, 360
    out.append(rect(bx, by, bw, bh, "#e8f5e9", "#2e7d32", 14))
    out.append(text(bx + 20, by + bh - 18, "Raspberry Pi 5", 20, weight="bold", fill="#1b5e20"))
    out.append(rect(bx + bw - 70, by + 40, 80, 190, "#cfd8dc", "#546e7a", 4))
    out.append(text(bx + bw - 26, by + 135, "USB / Ethernet", 11, "middle", fill="#37474f",
                    ).replace("<text ", f'<text transform="rotate(-90 {bx + bw - 26} {by + 135})" '))
    # the 40-pin header
    used = {p for p, *_ in HEADER_WIRES}
    out.append(rect(HDR_X - 13, HDR_Y - PITCH - 13, 19 * PITCH + 26, PITCH + 26, "#263238", "#263238", 3))
    for pin in range(1, 41):
        x, y = header_pin_xy(pin)
        colour = next((c for p, _, _, c in HEADER_WIRES if p == pin), "#b0bec5")
        if pin == 1:
            out.append(f'<rect x="{x - 6}" y="{y - 6}" width="12" height="12" fill="{colour}" stroke="white"/>')
        else:
            out.append(f'<circle cx="{x}" cy="{y}" r="6" fill="{colour}" '
                       f'stroke="{"white" if pin in used else "none"}"/>')
    out.append(text(HDR_X - 16, HDR_Y + 5, "1", 12, "end", "bold"))
    out.append(text(HDR_X - 16, HDR_Y - PITCH + 5, "2", 12, "end", "bold"))
    out.append(text(HDR_X + 19 * PITCH + 18, HDR_Y + 5, "39", 12, weight="bold"))
    out.append(text(HDR_X + 19 * PITCH + 18, HDR_Y - PITCH + 5, "40", 12, weight="bold"))
    out.append(text(HDR_X - 12, HDR_Y + 36, "40-pin GPIO header (pin 1: square pad; odd pins on the inner row)",
                    12, fill="#1b5e20"))
    out.append(text(HDR_X - 12, HDR_Y + 54, "used: 1 = 3V3, 3 = GPIO2 SDA1, 5 = GPIO3 SCL1, 6 = GND", 12,
                    weight="bold", fill="#1b5e20"))

    # the MPU-6050 breakout
    mh = (len(MPU_PINS) - 1) * MPU_STEP + 50
    out.append(rect(MPU_X, MPU_Y - 25, 170, mh, "#e3f2fd", "#1565c0", 8))
    out.append(text(MPU_X + 100, MPU_Y - 40, "MPU-6050 breakout (GY-521)", 14, "middle", "bold", "#0d47a1"))
    out.append(rect(MPU_X + 85, MPU_Y + 70, 60, 60, "#212121", "#212121", 3))
    out.append(text(MPU_X + 115, MPU_Y + 150, "MPU-6050", 12, "middle", fill="#0d47a1"))
    for name in MPU_PINS:
        x, y = mpu_pin_xy(name)
        out.append(f'<circle cx="{x}" cy="{y}" r="6" fill="#fbc02d" stroke="#6d4c00"/>')
        out.append(text(x + 14, y + 5, name, 13, weight="bold"))

    # the four header wires: up between the pins, along a run above the board, down to the breakout.
    # The leftmost wire takes the highest run; the breakout's top pin takes the rightmost descent.
    by_x = sorted(HEADER_WIRES, key=lambda w: header_pin_xy(w[0])[0] + (10 if w[0] % 2 else 0))
    for k, (pin, signal, mpu_pin, colour) in enumerate(by_x):
        x0, y0 = header_pin_xy(pin)
        up_x = x0 + PITCH / 2 if pin % 2 else x0  # an inner-row wire passes between the edge-row pins
        lane_y = LANE_Y + k * LANE_STEP
        lane_x = MPU_X - 30 - MPU_PINS.index(mpu_pin) * 14
        x1, y1 = mpu_pin_xy(mpu_pin)
        pts = [(x0, y0)] + ([(up_x, y0 - PITCH / 2)] if up_x != x0 else []) + \
              [(up_x, lane_y), (lane_x, lane_y), (lane_x, y1), (x1, y1)]
        out.append(polyline(pts, colour))
        out.append(dot(x0, y0, colour))
        out.append(dot(x1, y1, colour))
        out.append(text(250 + k * 70, lane_y - 3, f"pin {pin} {signal} -> {mpu_pin}", 10, fill=colour,
                        weight="bold"))
    # AD0 sets the address: low -> 0x68, high -> 0x69
    ad0_to = "GND" if address == 0x68 else "VCC"
    xa, ya = mpu_pin_xy("AD0")
    xg, yg = mpu_pin_xy(ad0_to)
    jx = MPU_X - 14
    out.append(polyline([(xa, ya), (jx, ya), (jx, yg + 6), (xg - 4, yg + 6)], "#6a1b9a", 2.5))
    out.append(dot(xa, ya, "#6a1b9a"))
    out.append(text(jx - 6, ya - 2, f"AD0 to {ad0_to}", 11, "end", "bold", "#6a1b9a"))
    out.append(text(jx - 6, ya + 12, f"(address {address:#04x})", 11, "end", "bold", "#6a1b9a"))
    # INT is optional and unused
    xi, yi = mpu_pin_xy("INT")
    out.append(polyline([(xi, yi), (xi - 40, yi)], "#9e9e9e", 2.0, 'stroke-dasharray="6,4"'))
    out.append(text(xi - 46, yi + 4, "INT: not connected", 11, "end", fill="#757575"))
    out.append(text(xi - 46, yi + 18, "(optional, unused)", 11, "end", fill="#757575"))
    out.append(text(MPU_X + 85, MPU_Y + mh - 10, "XDA / XCL: not connected", 11, "middle", fill="#555"))

    # the two CSI connectors and cameras
    conns = [("CAM/DISP 0", 270, "left camera", 110, "dtoverlay=imx296,cam0"),
             ("CAM/DISP 1", 410, "right camera", 410, "dtoverlay=imx296")]
    for label, cx, cam, camx, overlay in conns:
        cy = BOARD_Y + 180
        out.append(rect(cx - 22, cy, 44, 14, "#fafafa", "#424242", 2))
        out.append(text(cx, cy - 8, label, 12, "middle", "bold", "#212121"))
        cam_y = 585
        out.append(polyline([(cx, cy + 14), (cx, 535), (camx + 70, 535), (camx + 70, cam_y)], "#ffb74d", 14,
                            'stroke-opacity="0.85"'))
        out.append(rect(camx, cam_y, 140, 90, "#eceff1", "#37474f", 6))
        out.append(f'<circle cx="{camx + 70}" cy="{cam_y + 45}" r="24" fill="#263238"/>')
        out.append(f'<circle cx="{camx + 70}" cy="{cam_y + 45}" r="10" fill="#607d8b"/>')
        out.append(text(camx + 70, cam_y + 110, f"{cam} -> {label}", 13, "middle", "bold"))
        out.append(text(camx + 70, cam_y + 127, overlay, 11, "middle", fill="#555"))
    out.append(text(340, BOARD_Y + 230, "22-pin 0.5 mm FPC connectors", 11, "middle", fill="#1b5e20"))
    out.append(text(340, BOARD_Y + 245, "(a camera with a 15-pin socket", 11, "middle", fill="#1b5e20"))
    out.append(text(340, BOARD_Y + 260, "needs a 22-to-15-pin cable)", 11, "middle", fill="#1b5e20"))
    # baseline between the two lenses
    ly = 570
    out.append(polyline([(180, ly), (480, ly)], "#455a64", 1.5,
                        'marker-start="url(#arrow)" marker-end="url(#arrow)"'))
    out.insert(1, '<defs><marker id="arrow" viewBox="0 0 10 10" refX="5" refY="5" markerWidth="7" '
                  'markerHeight="7" orient="auto-start-reverse"><path d="M0,0 L10,5 L0,10 z" fill="#455a64"/>'
                  '</marker></defs>')
    out.append(text(330, ly - 6, "baseline (rig YAML: T_cam1_cam0)", 11, "middle", fill="#455a64"))

    # notes
    nx, ny = 640, 520
    notes = [
        ("bold", f"I2C: /dev/i2c-{bus}, address {address:#04x}"),
        ("normal", "config.txt: dtparam=i2c_arm=on,"),
        ("normal", "  dtparam=i2c_arm_baudrate=400000"),
        ("normal", f"device.toml [imu]: bus = {bus}, address = {address:#04x}"),
        ("normal", "Power the breakout from 3V3 (pin 1), not 5 V:"),
        ("normal", "  the Pi's GPIO pins are 3.3 V only."),
        ("bold", "Compute Module 4 (on the CM4 IO board):"),
        ("normal", "  the same header pins (1, 3, 5, 6) and i2c-1;"),
        ("normal", "  cameras on the IO board's 22-pin CAM0 / CAM1."),
    ]
    for i, (weight, line) in enumerate(notes):
        out.append(text(nx, ny + i * 18, line, 12, weight=weight))
    out.append("</svg>")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "img" / "wiring.svg"))
    parser.add_argument("--device-toml", default=str(ROOT / "firmware_cfg" / "device.toml"))
    args = parser.parse_args(argv)
    bus, address = imu_settings(Path(args.device_toml))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(draw(bus, address), encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
