"""An agent that ends without `finish_episode`, for server/app/tests/agent_quits.rs; launched by `libero-agent run
--harness command` in the sandbox like any harness (Python's standard library speaking streamable HTTP).

  kill   starts the episode, acts once, then kills its whole process group (its "CLI" included) with SIGKILL
  model  asks the model API once through the runner's gateway (the test points it at a port where nothing
         listens), then exits 1, as a CLI does when its provider fails

Nothing here may contain a brace-wrapped runner placeholder name: the runner substitutes those in the agent command
this script is inlined into.
"""
import json
import os
import signal
import sys
import urllib.error
import urllib.request

# From tests/clis/mcp_http.py, inlined before this script: WS, OPENER, rpc, initialize, call.


if sys.argv[1] == "kill":
    initialize("quitting-agent")
    call("start_episode", {})
    call("osc_sequence", {"actions": [[0.0, 0.0, -0.5, 0.0, 0.0, 0.0, -1.0]]})
    print("acted once; now killing my own process group", flush=True)
    os.killpg(0, signal.SIGKILL)
elif sys.argv[1] == "model":
    base = os.environ["LIBERO_MODEL_API_BASE"]
    req = urllib.request.Request(base.rstrip("/") + "/chat/completions", method="POST",
                                 data=json.dumps({"model": "m", "messages": [{"role": "user", "content": "hi"}]}).encode(),
                                 headers={"Content-Type": "application/json",
                                          "Authorization": "Bearer " + os.environ.get("LIBERO_MODEL_API_KEY", "")})
    try:
        OPENER.open(req, timeout=60).read()
        print("the model answered", flush=True)
    except urllib.error.HTTPError as e:
        print(f"the model API failed: HTTP {e.code}", flush=True)
    except OSError as e:
        print(f"the model API failed: {e}", flush=True)
    sys.exit(1)
