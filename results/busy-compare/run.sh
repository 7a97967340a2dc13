#!/bin/bash
# issue 30's must-show, on this machine: two identical sweeps quiet, one with a two-core hog, one pinned to one core
cd /work/main; . .venv/bin/activate
rm -f /tmp/m/*.csv
S="--backends numpy,c --grids 32,64 --steps 100 --repeat 10"
clothbench machine | tail -1
clothbench sweep $S --out /tmp/m/a.csv > /tmp/m/a.log 2>&1
clothbench sweep $S --out /tmp/m/b.csv > /tmp/m/b.log 2>&1
echo "== quiet A vs quiet B"; clothbench compare /tmp/m/a.csv /tmp/m/b.csv --fail-above 1.10 > /tmp/m/ab.txt; echo "exit $?"; grep -E "inconclusive|significant|slower than" /tmp/m/ab.txt
python3 -c "while True: pass" & H1=$!; python3 -c "while True: pass" & H2=$!
clothbench sweep $S --out /tmp/m/c.csv > /tmp/m/c.log 2>&1
kill $H1 $H2
echo "== quiet A vs hogged C"; clothbench compare /tmp/m/a.csv /tmp/m/c.csv --fail-above 1.10 > /tmp/m/ac.txt; echo "exit $?"; grep -E "inconclusive|significant|slower than" /tmp/m/ac.txt
taskset -c 0 clothbench sweep $S --out /tmp/m/d.csv > /tmp/m/d.log 2>&1
echo "== quiet A vs pinned D"; clothbench compare /tmp/m/a.csv /tmp/m/d.csv --fail-above 1.10 > /tmp/m/ad.txt; echo "exit $?"; grep -E "inconclusive|significant|slower than" /tmp/m/ad.txt
