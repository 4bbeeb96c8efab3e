"""Build the extension zips with Blender's own tool, one per platform, with the
ONNX Runtime and ``soundfile`` wheels (and their dependencies, never numpy:
Blender ships it) and the pure-Python ``python-osc`` wheel of the live receiver.

    python -m tools.build_extension [-o dist] [--platform NAME] [--no-wheels]

Steps: stage the tracked files of the checkout (``git ls-files``; the models
are tracked) in a temporary folder, download the wheels for each platform with
pip into ``cache/wheels`` (reused on the next build), list them in the staged
manifest, then run Blender's ``extension build --split-platforms`` and
``extension validate`` on every zip. Blender's tool is reached through the
``bpy`` module (``bl_pkg``) in a subprocess.

A developer tool, not part of the extension (``/tools/`` is excluded from the
zip); it may import the core, never the reverse.
"""
from __future__ import annotations

import argparse
import glob
import os
import shutil
import subprocess
import sys
import tempfile

from dancing_points_addon.errors import InputError, UserError, error_message

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
ONNXRUNTIME = "onnxruntime==1.22.1"
# The songs' decoder (libsndfile inside the wheel: WAV, FLAC, OGG, MP3) with its cffi and pycparser.
SOUNDFILE = "soundfile==0.14.0"
PLATFORM_WHEELS = (ONNXRUNTIME, SOUNDFILE)  # one build per platform, with their dependencies (never numpy)
PURE_WHEELS = ("python-osc==1.10.2",)  # pure Python (py3-none-any): one wheel for every platform
# Blender platform -> the pip platform tags its wheels may have (cffi's Linux wheel is manylinux_2_17)
PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_17_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_13_0_arm64", "macosx_14_0_arm64"],
}
PYTHON = "3.11"
_BLENDER_CLI = ("import sys, bpy\nfrom bl_pkg.bl_extension_cli import cli_extension_handler\n"
                "sys.exit(cli_extension_handler(sys.argv[1:]))\n")


def blender_extension_cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    """Run ``blender --command extension ARGS`` through the bpy module."""
    return subprocess.run([sys.executable, "-c", _BLENDER_CLI, *args], cwd=cwd, capture_output=True, text=True)


def tracked_files(root=ROOT) -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        raise InputError(root, "not a git checkout: cannot tell the extension's files") from None
    return [p for p in out.decode().split("\0") if p]


def download_wheels(platform: str, cache_dir: str) -> list[str]:
    """Wheels of onnxruntime, soundfile and their dependencies (no numpy) for one platform."""
    dest = os.path.join(cache_dir, platform)
    os.makedirs(dest, exist_ok=True)
    for req in PLATFORM_WHEELS:
        stem = req.split("==")[0].replace("-", "_") + "-"
        if glob.glob(os.path.join(dest, stem + "*.whl")):
            continue
        tags = [arg for tag in PLATFORMS[platform] for arg in ("--platform", tag)]  # any of them (a package
        res = subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--only-binary=:all:",  # and its deps)
                              "--python-version", PYTHON, "--implementation", "cp", *tags, "-d", dest, req],
                             capture_output=True, text=True)
        if res.returncode != 0:
            last = res.stderr.strip().splitlines()[-1:] or ["pip failed"]
            raise UserError(f"cannot download {req} for {platform}: {last[0]}")
    for req in PURE_WHEELS:
        stem = req.split("==")[0].replace("-", "_") + "-"
        if not glob.glob(os.path.join(dest, stem + "*.whl")):
            res = subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--only-binary=:all:", "--no-deps",
                                  "-d", dest, req], capture_output=True, text=True)
            if res.returncode != 0:
                last = res.stderr.strip().splitlines()[-1:] or ["pip failed"]
                raise UserError(f"cannot download {req}: {last[0]}")
    wheels = sorted(glob.glob(os.path.join(dest, "*.whl")))
    return [w for w in wheels if not os.path.basename(w).lower().startswith("numpy-")]


def unique_wheels(paths: list[str]) -> list[str]:
    """One file per wheel name; a project with a pure-Python wheel keeps only that
    one, so no platform's zip carries two builds of the same package."""
    by_name = {os.path.basename(p): p for p in paths}
    project = {n: n.split("-")[0].lower() for n in by_name}
    pure = {project[n] for n in by_name if n.endswith("-none-any.whl")}
    return [by_name[n] for n in sorted(by_name) if project[n] not in pure or n.endswith("-none-any.whl")]


def stage(dest: str, root=ROOT) -> None:
    for rel in tracked_files(root):
        src = os.path.join(root, rel)
        if not os.path.isfile(src):
            continue
        os.makedirs(os.path.dirname(os.path.join(dest, rel)), exist_ok=True)
        shutil.copy2(src, os.path.join(dest, rel))


def add_wheels_to_manifest(manifest_path: str, wheel_paths: list[str], platforms: list[str]) -> None:
    text = open(manifest_path, encoding="utf-8").read()
    lines = ["wheels = ["] + [f'  "./wheels/{os.path.basename(w)}",' for w in wheel_paths] + ["]",
             "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]", ""]
    # top-level keys must come before the first [table]
    i = text.index("\n[")
    text = text[:i + 1] + "\n".join(lines) + "\n" + text[i + 1:]
    with open(manifest_path, "w", encoding="utf-8") as f:
        f.write(text)


def build(out_dir: str = "dist", wheels: bool = True, platforms=None, cache_dir=None, log=print) -> list[str]:
    """Build the zips into ``out_dir``; returns their paths."""
    platforms = list(platforms or PLATFORMS)
    cache_dir = cache_dir or os.path.join(ROOT, "cache", "wheels")
    out_dir = os.path.abspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        src = os.path.join(tmp, "dancing_points")
        stage(src)
        args = ["build", "--source-dir", src, "--output-dir", out_dir]
        if wheels:
            os.makedirs(os.path.join(src, "wheels"))
            all_wheels = unique_wheels([w for p in platforms for w in download_wheels(p, cache_dir)])
            for w in all_wheels:
                shutil.copy2(w, os.path.join(src, "wheels"))
            log(f"{len(all_wheels)} wheels for {', '.join(platforms)}")
            add_wheels_to_manifest(os.path.join(src, "blender_manifest.toml"), all_wheels, platforms)
            args.append("--split-platforms")
        before = set(glob.glob(os.path.join(out_dir, "*.zip")))
        res = blender_extension_cli(*args)
        if res.returncode != 0:
            raise UserError("extension build failed: " + " ".join((res.stderr or res.stdout).split())[-400:])
        zips = sorted(set(glob.glob(os.path.join(out_dir, "*.zip"))) - before) or \
            sorted(glob.glob(os.path.join(out_dir, "dancing_points-*.zip")))
        for z in zips:
            v = blender_extension_cli("validate", z)
            if v.returncode != 0:
                raise InputError(z, "Blender's validator rejects the zip: " + " ".join(v.stdout.split())[-300:])
            log(f"built {z} ({os.path.getsize(z) / 1e6:.1f} MB), validated")
        return zips


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.build_extension",
                                 description="Build the extension with Blender's own 'extension build', one zip per "
                                             "platform with the ONNX Runtime wheels bundled, and validate each zip.")
    ap.add_argument("-o", "--output", default="dist", metavar="DIR", help="output folder (default dist)")
    ap.add_argument("--platform", action="append", metavar="NAME", choices=list(PLATFORMS),
                    help="linux-x64, windows-x64 or macos-arm64 (repeatable; default all three)")
    ap.add_argument("--no-wheels", action="store_true", help="one zip without bundled wheels")
    args = ap.parse_args(argv)
    try:
        zips = build(args.output, wheels=not args.no_wheels, platforms=args.platform or list(PLATFORMS))
    except UserError as exc:
        print(f"error: {error_message(exc)}", file=sys.stderr)
        return 2
    print("\n".join(zips))
    return 0


if __name__ == "__main__":
    sys.exit(main())
