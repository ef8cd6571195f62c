#!/usr/bin/env bash
# The Debian packages the tests run for real, installed when missing:
#   chromium                 the dashboard's browser test
#   prometheus               promtool (rule unit tests) and prometheus
#   prometheus-alertmanager  a real Alertmanager 0.25 and amtool (alert lifecycle tests)
#   jq                       the documentation's curl examples (tests/docs runs them)
# The tests start their own processes on 127.0.0.1 ephemeral ports with temporary data
# directories; the system services these packages ship are not used, so they are kept from
# starting on install (policy-rc.d) and stopped if they run anyway.
# Without root or apt (a developer's laptop) it says what is missing; the tests that need it
# then skip with that reason, but fail under CI (CI=true).
set -u
missing=()
command -v chromium >/dev/null 2>&1 || missing+=(chromium)
{ command -v promtool >/dev/null 2>&1 && command -v prometheus >/dev/null 2>&1; } || missing+=(prometheus)
{ command -v prometheus-alertmanager >/dev/null 2>&1 && command -v amtool >/dev/null 2>&1; } \
  || missing+=(prometheus-alertmanager)
command -v jq >/dev/null 2>&1 || missing+=(jq)
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
  echo "missing ${missing[*]} and cannot install here (needs root and apt-get); the tests that need them will skip" >&2
  exit 0
fi
echo "installing Debian's ${missing[*]} for the tests..."
# Keep the packages' services from starting: the tests run their own instances.
policy=/usr/sbin/policy-rc.d
own_policy=0
if [ ! -e "$policy" ]; then
  printf '#!/bin/sh\nexit 101\n' >"$policy" && chmod 755 "$policy" && own_policy=1
fi
(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
    -o DPkg::Lock::Timeout=300 --no-install-recommends "${missing[@]}" >/dev/null) \
  || echo "could not install ${missing[*]}; the tests that need them will skip" >&2
[ "$own_policy" = 1 ] && rm -f "$policy"
# Where a service manager started them anyway, stop and disable them (nothing depends on them).
for unit in prometheus prometheus-alertmanager; do
  if command -v systemctl >/dev/null 2>&1 && systemctl is-active --quiet "$unit" 2>/dev/null; then
    systemctl disable --now "$unit" >/dev/null 2>&1 || true
  elif [ -x "/etc/init.d/$unit" ]; then
    "/etc/init.d/$unit" stop >/dev/null 2>&1 || true
  fi
done
exit 0
