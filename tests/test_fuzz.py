"""Fuzzing the readers: a few hundred random and mutated take files
(CSV) and BVH files, with a fixed seed, through ``load_input`` in-process and a
sample of them through ``python -m dancing_points_addon extract``.

In-process, only success or an :class:`InputError` (one line, naming the file)
may come out, with no warning of any kind; a take that loads passes the
synthesis rules (``check_take``), resamples, and writes as text that reads back
with the same times and tracking. On the command line: exit status 0 or 2, no
traceback, one ``error:`` line on stderr and no file at the output path after a
failure, and the same outcome as in-process.
"""
import os
import time
import warnings

import numpy as np

from conftest import SALSA
from support.helpers import run_cli
from dancing_points_addon.errors import InputError
from dancing_points_addon.formats.asf_amc import load_amc
from dancing_points_addon.formats.bvh import write_bvh
from dancing_points_addon.inputs import check_take, load_input
from dancing_points_addon.formats.take import COLUMNS, Take, take_to_text
from dancing_points_addon.formats.take_read import parse_take_bytes
from dancing_points_addon.resample import resample_take
from dancing_points_addon.skeleton import Motion

SEED = 15
N_CSV = 320
N_BVH = 160
N_CLI = 20

NUMBERS = ["1e308", "-1e308", "1.7976931348623157e308", "1e400", "-1e400", "1e-400", "nan", "NaN", "inf",
           "-inf", "Infinity", "", " ", "0", "-0", "1e", "--1", "0x1p3", "1_0", "1,5", "१", "½", "9" * 400,
           "1e300", "-1e300", "1e10", "1.7e9", "abc", "\t", "0.5 0.5", "+.5", "5.", "1e-320", "\x7f", "é"]
JUNK_LINES = ["", "   ", "#", "# height_m=", "# height_m=1e9", "# height_m=0.001", "# height_m=abc",
              "# height_m=1.8", "# height_m=nan", "# =x", "#key=value", "# k=v=w", "time", ",,,,", "\ufeff#bom",
              ",".join(COLUMNS), ",".join(reversed(COLUMNS)), "\x00", "x" * 300, "# " + "é" * 50]


def _base_take(rng, n):
    t = np.cumsum(rng.uniform(0.008, 0.014, n)) + rng.choice([0.0, 0.0, 12.5, 1.7e9])
    pos = rng.uniform(-2, 2, (n, 3, 3))
    q = rng.normal(size=(n, 3, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    if rng.random() < 0.5:
        k = int(rng.integers(0, n))
        d = int(rng.integers(0, 3))
        pos[k:k + int(rng.integers(1, 6)), d] = np.nan
        q[k:k + int(rng.integers(1, 6)), d] = np.nan
    return Take(t, pos, q, {"height_m": 1.75} if rng.random() < 0.5 else {})


def _scaled(line, factor):
    f = line.split(",")
    if len(f) != len(COLUMNS) or not f[0][:1].isdigit():
        return line
    try:
        return ",".join([f[0]] + [repr(float(x) * factor) if x.strip() else x for x in f[1:]])
    except ValueError:
        return line


BENIGN = ["", "   ", "\t", "# a note", "#", "# key=value", "# height_m=1.8", "# height_m = 2.05 ", "#,,,,"]


def _mutate_csv(rng, text: str, benign_only=False) -> bytes:
    lines = text.split("\n")
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(14, 17) if benign_only else rng.integers(0, 17))
        k = int(rng.integers(0, len(lines))) if lines else 0
        if op == 14:  # the columns in another order (header and rows alike): still valid
            perm = rng.permutation(len(COLUMNS))
            lines = [",".join(f[i] for i in perm) if len(f := ln.split(",")) == len(COLUMNS) else ln
                     for ln in lines]
        elif op == 15:  # comments, metadata and blank lines anywhere
            for _ in range(int(rng.integers(1, 5))):
                lines.insert(int(rng.integers(0, len(lines) + 1)), str(rng.choice(BENIGN)))
        elif op == 16:  # spaces around every field
            pad = str(rng.choice([" ", "\t", "  "]))
            lines = [pad + ln.replace(",", pad + "," + pad) + pad if ln[:1].isdigit() else ln for ln in lines]
        elif op == 0 and lines:  # truncated line
            lines[k] = lines[k][:int(rng.integers(0, len(lines[k]) + 1))]
        elif op == 1:  # truncated file
            s = "\n".join(lines)
            lines = s[:int(rng.integers(0, len(s) + 1))].split("\n")
        elif op == 2 and lines:  # a field replaced by a strange number
            f = lines[k].split(",")
            f[int(rng.integers(0, len(f)))] = str(rng.choice(NUMBERS))
            lines[k] = ",".join(f)
        elif op == 3 and lines:  # a column removed (header or row)
            f = lines[k].split(",")
            if len(f) > 1:
                del f[int(rng.integers(0, len(f)))]
            lines[k] = ",".join(f)
        elif op == 4 and lines:  # two columns swapped (in one line, or in every line)
            i, j = (int(x) for x in rng.integers(0, len(COLUMNS), 2))
            for m in ([k] if rng.random() < 0.5 else range(len(lines))):
                f = lines[m].split(",")
                if max(i, j) < len(f):
                    f[i], f[j] = f[j], f[i]
                lines[m] = ",".join(f)
        elif op == 5:  # a comment, metadata or junk line
            lines.insert(k, str(rng.choice(JUNK_LINES)))
        elif op == 6 and len(lines) > 1:  # a line removed or duplicated
            if rng.random() < 0.5:
                del lines[k]
            else:
                lines.insert(k, lines[int(rng.integers(0, len(lines)))])
        elif op == 7 and lines:  # random printable junk
            lines[k] = "".join(chr(int(c)) for c in rng.integers(32, 127, int(rng.integers(0, 80))))
        elif op == 8:  # rows reversed (time decreasing)
            lines = lines[:3] + lines[3:][::-1]
        elif op == 9 and lines:  # a time far away: a gap, an epoch, 1e300
            f = lines[k].split(",")
            try:
                f[0] = repr(float(f[0]) + float(rng.choice([11.0, 86400.0, 1.7e9, 1e300, -1e300, 5e15])))
            except ValueError:
                f[0] = "1e300"
            lines[k] = ",".join(f)
        elif op == 10:  # every device lost on every row
            lines = [",".join(ln.split(",")[:1] + [""] * 21) if ln[:1].isdigit() else ln for ln in lines]
        elif op == 11:  # a short take
            lines = lines[:int(rng.integers(0, 6))]
        elif op == 12 and lines:  # trailing or inner whitespace, tabs
            lines[k] = lines[k].replace(",", rng.choice([", ", " ,", ",\t", ",  "]))
        elif op == 13:  # a bigger scale: every number of the rows times 1000 (millimetres)
            lines = [_scaled(ln, 1000.0) for ln in lines]
    data = "\n".join(lines).encode("utf-8", "surrogatepass")
    enc = rng.random()
    if enc < 0.15:
        data = data.replace(b"\n", b"\r\n")
    elif enc < 0.2:
        data = data.replace(b"\n", b"\r")
    if rng.random() < 0.1:
        data = b"\xef\xbb\xbf" + data
    if rng.random() < 0.05:  # random bytes spliced in
        i = int(rng.integers(0, len(data) + 1))
        data = data[:i] + rng.bytes(int(rng.integers(1, 40))) + data[i:]
    return data


def csv_cases(rng):
    """(name, bytes) of valid, mutated and random take files."""
    cases = []
    for k in range(N_CSV):
        r = rng.random()
        if k == 0:
            data = b""
        elif k == 1:
            data = rng.bytes(5000)
        elif k == 2:
            data = b"\x00" * 100
        elif k == 3:
            data = b"\xef\xbb\xbf"
        elif r < 0.04:  # binary
            data = rng.bytes(int(rng.integers(1, 3000)))
        elif r < 0.07:  # random text
            data = bytes(rng.integers(9, 127, int(rng.integers(1, 3000))).astype(np.uint8))
        else:
            text = take_to_text(_base_take(rng, int(rng.integers(2, 80))))
            data = (text.encode() if r < 0.1 else _mutate_csv(rng, text, benign_only=r < 0.4))
        cases.append((f"take_{k:03d}.csv", data))
    return cases


def _small_motion():
    m = load_amc(SALSA / "60_01.amc")
    return Motion(m.positions[:12], m.rotations[:12], m.fps, m.bone_vectors)


def _mutate_bvh(rng, lines, benign_only=False):
    lines = list(lines)
    motion = next(i for i, ln in enumerate(lines) if ln.startswith("MOTION"))
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(11, 14) if benign_only else rng.integers(0, 14))
        if op == 11:  # blank lines and other indentation: still valid
            lines = [("  " + ln.strip()) if rng.random() < 0.5 else ln for ln in lines]
            lines.insert(int(rng.integers(0, len(lines) + 1)), "")
        elif op == 12:  # a frame rate within the bounds
            i = next((i for i, ln in enumerate(lines) if ln.startswith("Frame Time")), None)
            if i is not None:
                lines[i] = "Frame Time: " + str(rng.choice(["0.0083333", "0.05", "0.5", "0.001"]))
        elif op == 13:  # braces on the keyword lines
            lines = [ln.rstrip() + " {" if ln.strip().startswith(("ROOT", "JOINT")) else ln for ln in lines]
            lines = [ln for i, ln in enumerate(lines)
                     if not (ln.strip() == "{" and i and lines[i - 1].endswith(" {"))]
        k = int(rng.integers(0, len(lines))) if lines else 0
        if op == 0:  # a brace removed, or one added
            braces = [i for i, ln in enumerate(lines) if ln.strip() in ("{", "}")]
            if braces and rng.random() < 0.7:
                del lines[int(rng.choice(braces))]
            else:
                lines.insert(k, rng.choice(["{", "}"]))
        elif op == 1 and lines:  # a bad number in a frame row or an OFFSET
            toks = lines[k].split()
            if toks:
                toks[int(rng.integers(0, len(toks)))] = str(rng.choice(NUMBERS)) or "x"
                lines[k] = " ".join(toks)
        elif op == 2:  # wrong channel count
            ch = [i for i, ln in enumerate(lines) if "CHANNELS" in ln]
            i = int(rng.choice(ch))
            toks = lines[i].split()
            toks[1] = str(int(rng.integers(-1, 9)))
            lines[i] = "\t" + " ".join(toks)
        elif op == 3:  # a value missing or extra in a frame row
            rows = list(range(motion + 3, len(lines)))
            if rows:
                i = int(rng.choice(rows))
                toks = lines[i].split()
                if rng.random() < 0.5 and toks:
                    del toks[int(rng.integers(0, len(toks)))]
                else:
                    toks.append("0")
                lines[i] = " ".join(toks)
        elif op == 4:  # truncated
            lines = lines[:int(rng.integers(0, len(lines) + 1))]
            if lines and rng.random() < 0.5:
                lines[-1] = lines[-1][:int(rng.integers(0, len(lines[-1]) + 1))]
        elif op == 5:  # Frame Time
            i = next((i for i, ln in enumerate(lines) if ln.startswith("Frame Time")), None)
            if i is not None:
                lines[i] = "Frame Time: " + str(rng.choice(["0", "-1", "1e6", "1e-300", "nan", "inf", "2", "0.001",
                                                             "1e-4", "0.0083333", "x", "1e400"]))
        elif op == 6:  # Frames
            i = next((i for i, ln in enumerate(lines) if ln.startswith("Frames")), None)
            if i is not None:
                lines[i] = "Frames: " + str(rng.choice(["0", "1", "2", "100000000", "-3", "x", "11", "13",
                                                         "99999999999999999999999"]))
        elif op == 7 and len(lines) > 1:  # a line removed or duplicated
            if rng.random() < 0.5:
                del lines[k]
            else:
                lines.insert(k, lines[int(rng.integers(0, len(lines)))])
        elif op == 8 and lines:  # junk tokens
            lines[k] = str(rng.choice(["ROOT X", "JOINT", "End Site", "OFFSET", "CHANNELS 9", "MOTION",
                                       "HIERARCHY", "x y z", "\x00", "é"]))
        elif op == 9:  # huge values in a whole frame row
            rows = list(range(motion + 3, len(lines)))
            if rows:
                i = int(rng.choice(rows))
                lines[i] = " ".join(str(rng.choice(["1e308", "-1e308", "1e30", "0"])) for _ in lines[i].split())
        elif op == 10 and lines:  # a joint renamed (naming no longer recognised)
            i = next((i for i, ln in enumerate(lines) if "JOINT Head" in ln), None)
            if i is not None:
                lines[i] = lines[i].replace("Head", "Skull")
    nl = "\r\n" if rng.random() < 0.15 else "\n"
    return nl.join(lines).encode("utf-8", "surrogatepass")


def bvh_cases(rng, base_lines):
    cases = []
    for k in range(N_BVH):
        if k == 0:
            data = "\n".join(base_lines).encode()
        elif k == 1:
            data = b""
        elif k == 2:
            data = rng.bytes(4000)
        else:
            data = _mutate_bvh(rng, base_lines, benign_only=rng.random() < 0.2)
        cases.append((f"motion_{k:03d}.bvh", data))
    return cases


def _check_loaded(take, path):
    """What a successful load must give: a take that can be synthesised and written back."""
    assert take.n_frames >= 2
    assert np.isfinite(take.time).all() and (np.diff(take.time) > 0).all()
    valid = take.valid
    assert valid.any()
    assert np.all(np.linalg.norm(take.positions[valid], axis=-1) <= 1000.0)
    assert np.allclose(np.linalg.norm(take.quats[valid], axis=-1), 1.0)
    h = take.height
    assert h is None or 0.5 <= h <= 3.0
    check_take(take, path)
    r = resample_take(take)
    assert r.n_frames >= 2 and r.valid.any()
    back = parse_take_bytes(take_to_text(take).encode(), path)  # what extract writes reads back
    assert np.array_equal(back.time, take.time) and np.array_equal(back.valid, valid)


def _load(path):
    """'ok' or the InputError's message; anything else (an exception or a warning) fails."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            take = load_input(path)
        except InputError as e:
            msg = str(e)
            assert msg.startswith(str(path)), msg
            assert "\n" not in msg and "\r" not in msg, msg
            return msg
        _check_loaded(take, str(path))
        return "ok"


def test_fuzz_readers_in_process_and_cli(tmp_path):
    t_start = time.perf_counter()
    rng = np.random.default_rng(SEED)
    m = _small_motion()
    base = tmp_path / "base.bvh"
    write_bvh(base, m)
    base_lines = base.read_text().splitlines()
    d = tmp_path / "in"
    d.mkdir()
    cases = csv_cases(rng) + bvh_cases(rng, base_lines)
    outcomes = {}
    for name, data in cases:
        p = d / name
        p.write_bytes(data)
        try:
            outcomes[name] = _load(p)
        except Exception as e:  # noqa: BLE001 - report which file
            raise AssertionError(f"{name}: {type(e).__name__}: {e}\n{data[:400]!r}") from e
    n_ok = sum(v == "ok" for v in outcomes.values())
    n_csv_ok = sum(v == "ok" for k, v in outcomes.items() if k.endswith(".csv"))
    n_bvh_ok = n_ok - n_csv_ok
    # Both outcomes are well represented.
    assert 30 < n_csv_ok < N_CSV - 60, n_csv_ok
    assert 3 <= n_bvh_ok < N_BVH - 30, n_bvh_ok
    t_mid = time.perf_counter()

    # A sample through the command line: half that loaded, half that did not.
    names = sorted(outcomes)
    ok = [n for n in names if outcomes[n] == "ok"]
    bad = [n for n in names if outcomes[n] != "ok"]
    pick = list(rng.choice(ok, N_CLI // 4, replace=False)) + list(rng.choice(bad, N_CLI - N_CLI // 4,
                                                                              replace=False))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    for name in pick:
        out = out_dir / (name + ".out.csv")
        res = run_cli("extract", d / name, "-o", out, timeout=60)
        assert "Traceback" not in res.stderr + res.stdout, (name, res.stderr)
        assert res.returncode in (0, 2), (name, res.returncode, res.stderr)
        if outcomes[name] == "ok":
            assert res.returncode == 0, (name, res.stderr)
            assert out.exists() and res.stderr == "", (name, res.stderr)
            assert _load(out) == "ok"
        else:
            assert res.returncode == 2, (name, res.stdout)
            lines = res.stderr.splitlines()
            expected = {f"error: {outcomes[name]}"}
            try:  # the command line may escape characters a terminal would act on
                from dancing_points_addon.argtypes import printable
                expected.add(printable(f"error: {outcomes[name]}"))
            except ImportError:
                pass
            assert len(lines) == 1 and lines[0] in expected, (name, res.stderr)
            assert not out.exists()
    assert not [f for f in os.listdir(out_dir) if f.startswith(".")]  # no temporary files left
    t_end = time.perf_counter()
    print(f"\nfuzz: {len(cases)} files ({n_csv_ok} of {N_CSV} takes and {n_bvh_ok} of {N_BVH} BVH files load) "
          f"in {t_mid - t_start:.1f} s in-process; {len(pick)} through the CLI in {t_end - t_mid:.1f} s")
