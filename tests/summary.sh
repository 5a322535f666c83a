#!/usr/bin/env bash
# Prints doctest's test-case counts from a log as the CI summary line "N passed, N failed".
line=$(grep -E '^\[doctest\] test cases:' "$1" | tail -n 1)
if [ -z "$line" ]; then echo "0 passed, 1 failed (the test binary did not finish)"; exit 0; fi
passed=$(sed -E 's/.*\| *([0-9]+) passed.*/\1/' <<<"$line")
failed=$(sed -E 's/.*\| *([0-9]+) failed.*/\1/' <<<"$line")
echo "$passed passed, $failed failed"
