#!/usr/bin/env bash
# Installs the Debian packages talkmesh uses, only those that are missing (idempotent).
#   espeak-ng             speech synthesis for the demo; drives the MBROLA voices
#   mbrola mbrola-us1 mbrola-us2 mbrola-us3 mbrola-en1
#                         synthetic voices with exact phone timings (contrib / non-free)
#   mbrola-af1 ... mbrola-tl1  the multilingual corpus's voices (talkmesh.audio.languages;
#                         never the voices reserved for outside checks)
#   festival festvox-*    four more synthetic voices with exact segment times (festvox-don: a fifth)
#   festvox-ellpc11k ... festvox-te-nsk  Festival voices of other languages for the multilingual
#                         corpus (talkmesh.audio.festival_voices; optional: skipped where the
#                         registry lacks them; never a Czech voice, reserved for outside checks)
#   flite libttspico-utils  more voices for corpora beyond 12 subjects (phones by forced alignment)
#   pocketsphinx-testdata real recorded speech (LibriVox clips) used by tests and docs
#   alsa-utils            more real speech (/usr/share/sounds/alsa/*.wav)
#   nodejs npm            the Khronos glTF validator used by the tests; builds the browser viewer
#   chromium              the browser the viewer's end-to-end test drives (tests/test_browser.py)
set -euo pipefail
pkgs=(espeak-ng pocketsphinx-testdata alsa-utils
      mbrola mbrola-us1 mbrola-us2 mbrola-us3 mbrola-en1
      mbrola-af1 mbrola-ar1 mbrola-ar2 mbrola-br3 mbrola-br4 mbrola-cr1 mbrola-de2 mbrola-de3
      mbrola-de4 mbrola-de6 mbrola-ee1 mbrola-es2 mbrola-es3 mbrola-fr2 mbrola-fr4 mbrola-fr6
      mbrola-hb1 mbrola-hb2 mbrola-ic1 mbrola-id1 mbrola-in1 mbrola-in2 mbrola-ir1 mbrola-it1
      mbrola-it4 mbrola-jp1 mbrola-jp2 mbrola-jp3 mbrola-lt1 mbrola-lt2 mbrola-ma1 mbrola-mx1
      mbrola-nl1 mbrola-nl3 mbrola-pt1 mbrola-tl1
      festival festvox-kallpc16k festvox-kdlpc16k festvox-rablpc16k festvox-us-slt-hts festvox-don
      flite libttspico-utils
      chromium)
optional=(festvox-ellpc11k festvox-italp16k festvox-itapc16k festvox-ru festvox-suopuhe-lj
          festvox-suopuhe-mv festvox-ca-ona-hts festvox-hi-nsk festival-hi festvox-mr-nsk
          festival-mr festvox-te-nsk festival-te)
command -v node >/dev/null 2>&1 || pkgs+=(nodejs)
command -v npm >/dev/null 2>&1 || pkgs+=(npm)
missing=()
for p in "${pkgs[@]}" "${optional[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  # The MBROLA voices live in contrib / non-free: enable those components (deb822 or one-line sources).
  src=/etc/apt/sources.list.d/debian.sources
  if [ -f "$src" ] && grep -q '^Components: main$' "$src"; then
    $sudo sed -i 's/^Components: main$/Components: main contrib non-free/' "$src"
  elif [ -f /etc/apt/sources.list ] && grep -qE '^deb .* main$' /etc/apt/sources.list; then
    $sudo sed -i -E 's/^(deb .* main)$/\1 contrib non-free/' /etc/apt/sources.list
  fi
  $sudo apt-get update -qq
  wanted=()
  for p in "${missing[@]}"; do  # an optional package this registry lacks is skipped, not fatal
    if [[ " ${optional[*]} " == *" $p "* ]] && ! apt-cache show "$p" >/dev/null 2>&1; then
      echo "skipping $p: not in this machine's package registry"
    else
      wanted+=("$p")
    fi
  done
  if [ ${#wanted[@]} -gt 0 ]; then
    echo "installing Debian packages: ${wanted[*]}"
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${wanted[@]}" >/dev/null
  fi
fi
