#!/usr/bin/env bash
# Regenerate server/sim/tests/fixtures/placement_reference.json: the real LIBERO env's reset (fresh ControlEnv,
# env.seed(S), env.reset()) for a set of scenes and seeds covering every problem class and every sampler kind
# (fixtures, table regions with rejection, object/fixture sites, In, On-object, Open/Close/TurnOn initializers).
#   scripts/reference_stack/make_placement_fixtures.sh [VENV]
set -euo pipefail
CACHE="${LIBERO_AGENT_CACHE:-$HOME/.cache/libero-agent}"
VENV="${1:-$CACHE/refstack}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
B="$CACHE/hf-libero-0.1.4/bddl_files"
OUT="$HERE/../../server/sim/tests/fixtures/placement_reference.json"
TMP="$(mktemp -d)"
CASES=(
  "libero_spatial/pick_up_the_black_bowl_in_the_top_drawer_of_the_wooden_cabinet_and_place_it_on_the_plate 1"
  "libero_spatial/pick_up_the_black_bowl_on_the_cookie_box_and_place_it_on_the_plate 7"
  "libero_spatial/pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate 3"
  "libero_goal/open_the_top_drawer_and_put_the_bowl_inside 5"
  "libero_object/pick_up_the_ketchup_and_place_it_in_the_basket 2"
  "libero_10/KITCHEN_SCENE8_put_both_moka_pots_on_the_stove 11"
  "libero_10/KITCHEN_SCENE6_put_the_yellow_and_white_mug_in_the_microwave_and_close_it 4"
  "libero_10/LIVING_ROOM_SCENE1_put_both_the_alphabet_soup_and_the_cream_cheese_box_in_the_basket 9"
  "libero_90/KITCHEN_SCENE7_put_the_white_bowl_on_the_plate 6"
  "libero_90/KITCHEN_SCENE4_close_the_bottom_drawer_of_the_cabinet 12345"
  "libero_90/STUDY_SCENE4_pick_up_the_book_on_the_right_and_place_it_on_the_cabinet_shelf 8"
  "libero_90/LIVING_ROOM_SCENE6_put_the_red_mug_on_the_plate 10"
  "libero_90/STUDY_SCENE1_pick_up_the_yellow_and_white_mug_and_place_it_to_the_right_of_the_caddy 0"
  "libero_90/KITCHEN_SCENE9_put_the_frying_pan_on_top_of_the_cabinet 2"
)
i=0
for c in "${CASES[@]}"; do
  set -- $c
  "$VENV/bin/python" "$HERE/libero_env.py" --bddl "$B/$1.bddl" --seed "$2" --no-model --out "$TMP/$i.json" 2>/dev/null
  i=$((i+1))
done
"$VENV/bin/python" - "$TMP" "$OUT" <<'PY'
import json, sys, os, glob
rows = [json.load(open(f)) for f in sorted(glob.glob(sys.argv[1] + "/*.json"), key=lambda f: int(os.path.basename(f)[:-5]))]
for r in rows:
    r.pop("bddl", None); r.pop("rng_trace", None)
json.dump(rows, open(sys.argv[2], "w"), indent=0)
print("wrote", sys.argv[2], len(rows))
PY
