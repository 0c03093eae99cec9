"""An agent for the transcript test (server/app/tests/agent_transcript.rs), launched by `libero-agent run --harness
command` in the sandbox like any harness. It prints numbered lines, flushed, around each of its MCP calls (Python's
standard library speaking streamable HTTP), looks at the observation files as the paper's agents did (numpy, when
the toolbox is there), asks the model API once through the runner's gateway, and prints what a hostile agent would:
a line of 3 MiB, bytes that are not UTF-8, a usage line of its own making and its API key.

Nothing here may contain a brace-wrapped runner placeholder name: the runner substitutes those in the agent command
this script is inlined into.
"""
import json
import os
import sys
import time
import urllib.request

# From tests/clis/mcp_http.py, inlined before this script: WS, OPENER, rpc, initialize, call.
PAUSE_S = float(sys.argv[1]) if len(sys.argv) > 1 else 1.0


def say(text):
    """One line, flushed, then a pause so the runner captures it before the next call reaches the server."""
    print(text, flush=True)
    time.sleep(PAUSE_S)


say("agent line 1: reading TASK_PROMPT.txt")
initialize("transcript-agent")
say("agent line 2: starting the episode")
start = call("start_episode", {})
say(f"agent line 3: got {start['observation_id']}")
obs_dir = os.path.join(WS, "benchmark_inputs", "current_observation")
try:
    import numpy
    depth = numpy.load(os.path.join(obs_dir, "head", "depth_m.npy"))
    say(f"agent line 4: head depth {depth.shape} median {float(numpy.median(depth)):.3f} m")
except Exception as e:  # no toolbox: the line still says what happened
    say(f"agent line 4: no depth ({type(e).__name__})")
step = call("osc_sequence", {"actions": [[0.0, 0.0, -0.5, 0.0, 0.0, 0.0, -1.0]]})
say(f"agent line 5: moved, now {step['observation_id']}")

# The model API through the runner's gateway, once (the gateway records its usage).
base = os.environ.get("LIBERO_MODEL_API_BASE")
if base:
    req = urllib.request.Request(base.rstrip("/") + "/chat/completions", method="POST",
                                 data=json.dumps({"model": "scripted", "messages": [{"role": "user", "content": "hi"}]}).encode(),
                                 headers={"Content-Type": "application/json",
                                          "Authorization": "Bearer " + os.environ.get("LIBERO_MODEL_API_KEY", "")})
    reply = json.loads(OPENER.open(req, timeout=60).read())
    say(f"agent line 6: the model said {reply['choices'][0]['message']['content']!r}")

# What a hostile agent prints.
out = sys.stdout.buffer
out.write(b"y" * (3 << 20) + b"\n")
out.write(b"not utf-8: \xff\xfe\xc3\x28 end\n")
out.write(json.dumps({"type": "result", "usage": {"input_tokens": 999999999, "output_tokens": 999999999}}).encode() + b"\n")
out.write(("my key is " + os.environ.get("LIBERO_MODEL_API_KEY", "none") + "\n").encode())
out.flush()
say("agent line 7: finishing")
finish = call("finish_episode", {})
say(f"agent line 8: finished, success={finish['success']}")
