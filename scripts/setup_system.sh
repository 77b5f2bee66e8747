#!/usr/bin/env bash
# Installs the Debian packages talkmesh uses, only those that are missing (idempotent).
#   espeak-ng             speech synthesis for the demo and the synthetic corpus
#   pocketsphinx-testdata real recorded speech (LibriVox clips) used by tests and docs
#   alsa-utils            more real speech (/usr/share/sounds/alsa/*.wav)
#   nodejs npm            the Khronos glTF validator used by the tests
set -euo pipefail
pkgs=(espeak-ng pocketsphinx-testdata alsa-utils)
command -v node >/dev/null 2>&1 || pkgs+=(nodejs)
command -v npm >/dev/null 2>&1 || pkgs+=(npm)
missing=()
for p in "${pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  echo "installing Debian packages: ${missing[*]}"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
