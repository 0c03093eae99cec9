"""Throws malformed HTTP bodies, JSON-RPC messages and tool arguments at one episode endpoint. Every message
must get an error (an HTTP error status, a JSON-RPC error, or a tool result with isError) and the server
must stay up; finally a valid call still works. Run by `server/app/tests/mcp_python_client.rs`."""
import argparse
import json
import sys

import httpx2

ACCEPT = "application/json, text/event-stream"


def messages(resp):
    text = resp.text
    if resp.headers.get("content-type", "").startswith("text/event-stream"):
        out = []
        for event in text.split("\n\n"):
            data = [l[5:].lstrip() for l in event.splitlines() if l.startswith("data:")]
            if data and "".join(data).strip():
                out.append(json.loads("\n".join(data)))
        return out
    return [json.loads(text)] if text.strip() else []


def is_error(resp):
    if resp.status_code >= 400:
        return True
    msgs = messages(resp)
    return bool(msgs) and all("error" in m or (m.get("result") or {}).get("isError") is True for m in msgs)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--token", required=True)
    ap.add_argument("--health", required=True)
    a = ap.parse_args()
    base = {"Authorization": f"Bearer {a.token}", "Accept": ACCEPT, "Content-Type": "application/json"}
    failures = []
    sent = 0
    with httpx2.Client(timeout=60) as h:
        def alive():
            return h.get(a.health).status_code == 200

        def expect_error(body, headers, what):
            nonlocal sent
            sent += 1
            r = h.post(a.url, content=body, headers=headers)
            if not is_error(r):
                failures.append(f"{what}: HTTP {r.status_code} {r.text[:200]!r}")
            if not alive():
                print(json.dumps({"ok": False, "failed": f"server died after {what}"}))
                sys.exit(1)

        raw = [b"", b"{", b"[]", b"[1,2]", b"null", b"42", b'"x"', b'{"jsonrpc":"2.0"}', b'{"jsonrpc":"2.0","id":1}',
               b"\xff\xfe\x00", b'{"jsonrpc":"1.0","id":1,"method":"initialize"}', b"[" * 100000,
               b'{"jsonrpc":"2.0","id":1,"method":"tools/call","params":{"name":"start_episode"}}',
               b" " * (2 << 20)]
        for i, body in enumerate(raw):
            expect_error(body, base, f"raw body {i}")
        for hdr in ({"Accept": ACCEPT, "Content-Type": "application/json"},
                    {**base, "Authorization": "Bearer " + "0" * 64}, {**base, "Authorization": a.token}):
            expect_error(b'{"jsonrpc":"2.0","id":1,"method":"ping"}', hdr, f"bad auth {hdr.get('Authorization')!r}")

        init = {"jsonrpc": "2.0", "id": 1, "method": "initialize",
                "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "fuzz", "version": "0"}}}
        r = h.post(a.url, json=init, headers=base)
        assert r.status_code == 200, r.text
        sid = r.headers.get("mcp-session-id")
        s = {**base, "Mcp-Session-Id": sid, "Mcp-Protocol-Version": "2025-06-18"} if sid else dict(base)
        h.post(a.url, json={"jsonrpc": "2.0", "method": "notifications/initialized"}, headers=s)

        calls = [
            "x", [], {"name": 5}, {"name": "osc_sequence", "arguments": [1]},
            {"name": "osc_sequence", "arguments": {"actions": "[[0,0,0,0,0,0,0]]"}},
            {"name": "osc_sequence", "arguments": {"actions": [[0] * 7]}},  # before start
            {"name": "osc_sequence", "arguments": {"actions": [[1e308] * 7]}},
            {"name": "osc_sequence", "arguments": {"actions": [[None] * 7]}},
            {"name": "osc_sequence", "arguments": {"actions": {"0": [0] * 7}}},
            {"name": "finish_episode", "arguments": {"now": True}},
            {"name": "", "arguments": {}}, {"name": "../../etc/passwd"}, {"name": "osc_sequence\u0000"},
        ]
        for i, params in enumerate(calls):
            body = json.dumps({"jsonrpc": "2.0", "id": 100 + i, "method": "tools/call", "params": params}).encode()
            expect_error(body, s, f"tools/call {params!r}"[:120])
        for i, m in enumerate(["resources/list", "prompts/list", "tools/call/x", "", "sampling/createMessage"]):
            body = json.dumps({"jsonrpc": "2.0", "id": 200 + i, "method": m, "params": {}}).encode()
            expect_error(body, s, f"method {m!r}")
        expect_error(b'{"jsonrpc":"2.0","id":300,"method":"tools/call","params":{"name":"osc_sequence","arguments":{"actions":[[1e999]]}}}',
                     s, "number out of range")

        # The episode still works after all of that.
        body = json.dumps({"jsonrpc": "2.0", "id": 400, "method": "tools/call",
                           "params": {"name": "start_episode", "arguments": {}}}).encode()
        r = h.post(a.url, content=body, headers=s)
        ok = [m for m in messages(r) if m.get("id") == 400]
        if not ok or ok[0]["result"]["structuredContent"].get("ok") is not True:
            failures.append(f"valid start_episode after fuzzing failed: {r.text[:300]}")
    print(json.dumps({"ok": not failures, "sent": sent, "failures": failures}))
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
