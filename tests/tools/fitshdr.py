#!/usr/bin/python3
"""Edit FITS header cards byte for byte, for the bad-input tests (no FITS library: the point
is to write headers a FITS library would refuse to write).

usage: fitshdr.py IN OUT [--hdu N] [KEY=RAW ...] [-KEY ...]
       fitshdr.py IN OUT --nosum
       fitshdr.py IN OUT [--hdu N] --fill VALUE FRACTION [FIRST]
       fitshdr.py IN OUT [--hdu N] --copy-columns FROM TO COUNT
  KEY=RAW   set KEY's value field to RAW verbatim (e.g. PUPN=2147483648, WAVELEN=T,
            "CTYPE1='REAL'"), replacing the card or inserting it before END
  -KEY      delete the card
  --hdu N   the HDU to edit (1 = primary, default); its CHECKSUM and DATASUM cards are
            dropped, since the edit invalidates them
  --nosum   only drop CHECKSUM and DATASUM from every HDU (after an edit by other means)
  --fill VALUE FRACTION [FIRST]  set every (1/FRACTION)-th data value of the HDU (floating
            point BITPIX) to VALUE (nan, inf, 1.8e308, ...), from value FIRST (0-based, FITS
            order; default 0): FRACTION 1 sets all, FRACTION 0 only value FIRST
  --copy-columns FROM TO COUNT  in every row (along NAXIS1) of the HDU's image (floating
            point BITPIX), columns TO..TO+COUNT-1 (0-based) made copies of FROM..FROM+COUNT-1:
            a matrix of lower rank
A header that outgrows its 2880-byte blocks is refused (the tests never need that)."""
import sys


def hdus(data):
    """(header start, header end) of each HDU, walking headers only (data sizes from NAXISn)."""
    out, pos = [], 0
    while pos + 2880 <= len(data):
        end = None
        for k in range(pos, len(data), 80):
            if data[k:k + 8] == b"END     ":
                end = k
                break
        if end is None:
            break
        hend = (end // 2880 + 1) * 2880
        cards = {}
        for k in range(pos, end, 80):
            key = data[k:k + 8].decode("ascii", "replace").strip()
            val = data[k + 10:k + 80].decode("ascii", "replace").split("/")[0].strip()
            cards.setdefault(key, val)
        out.append((pos, end))
        try:
            naxis = int(cards.get("NAXIS", "0"))
            n = 1 if naxis else 0
            for i in range(1, naxis + 1):
                n *= int(cards["NAXIS%d" % i])
            if "PCOUNT" in cards and naxis:
                n += int(cards["PCOUNT"]) * 8 // abs(int(cards["BITPIX"]))
            size = n * abs(int(cards["BITPIX"])) // 8
        except (KeyError, ValueError):
            break
        pos = hend + (size + 2879) // 2880 * 2880
    return out


def main(argv):
    if len(argv) < 3:
        sys.exit(__doc__)
    src, dst, args = argv[1], argv[2], argv[3:]
    hdu = 1
    if len(args) >= 2 and args[0] == "--hdu":
        hdu, args = int(args[1]), args[2:]
    data = bytearray(open(src, "rb").read())
    if args == ["--nosum"]:
        for start, end in hdus(bytes(data)):
            for k in range(start, end, 80):
                if data[k:k + 8] in (b"CHECKSUM", b"DATASUM "):
                    data[k:k + 80] = b"COMMENT".ljust(80)
        open(dst, "wb").write(data)
        return
    start, end = hdus(bytes(data))[hdu - 1]
    if args[:1] == ["--copy-columns"]:
        cards = {}
        for k in range(start, end, 80):
            cards.setdefault(data[k:k + 8].decode().strip(), data[k + 10:k + 80].decode().split("/")[0].strip())
        size, nx, n = abs(int(cards["BITPIX"])) // 8, int(cards["NAXIS1"]), 1
        for i in range(1, int(cards["NAXIS"]) + 1):
            n *= int(cards["NAXIS%d" % i])
        src, to, count = (int(a) for a in args[1:4])
        if int(cards["BITPIX"]) > 0 or min(src, to) < 0 or max(src, to) + count > nx:
            sys.exit("fitshdr.py: --copy-columns needs floating point data and columns within NAXIS1")
        d0 = (end // 2880 + 1) * 2880
        for row in range(0, n, nx):
            a = d0 + row * size
            data[a + to * size:a + (to + count) * size] = data[a + src * size:a + (src + count) * size]
        args = []
    if args[:1] == ["--fill"]:
        import struct
        value, frac = float(args[1]), float(args[2])
        cards = {}
        for k in range(start, end, 80):
            cards.setdefault(data[k:k + 8].decode().strip(), data[k + 10:k + 80].decode().split("/")[0].strip())
        bitpix, n = int(cards["BITPIX"]), 1
        for i in range(1, int(cards["NAXIS"]) + 1):
            n *= int(cards["NAXIS%d" % i])
        fmt, size = {-64: (">d", 8), -32: (">f", 4)}[bitpix]
        step = max(1, round(1 / frac)) if frac > 0 else n
        first = int(args[3]) if len(args) > 3 else 0
        d0 = (end // 2880 + 1) * 2880
        for i in range(first, n, step):
            data[d0 + i * size:d0 + (i + 1) * size] = struct.pack(fmt, value)
        args = []
    cards = [bytes(data[k:k + 80]) for k in range(start, end, 80)]
    cards = [c for c in cards if c[:8] not in (b"CHECKSUM", b"DATASUM ")]
    for a in args:
        if a.startswith("-"):
            key = a[1:].ljust(8).encode()
            cards = [c for c in cards if c[:8] != key]
            continue
        key, raw = a.split("=", 1)
        card = (key.ljust(8) + "= " + raw.rjust(20)).ljust(80)[:80].encode()
        for i, c in enumerate(cards):
            if c[:8] == key.ljust(8).encode():
                cards[i] = card
                break
        else:
            cards.append(card)
    hlen = (end // 2880 + 1) * 2880 - start
    block = b"".join(cards) + b"END".ljust(80)
    if len(block) > hlen:
        sys.exit("fitshdr.py: the edited header needs more blocks than the original")
    data[start:start + hlen] = block.ljust(hlen)
    open(dst, "wb").write(data)


main(sys.argv)
