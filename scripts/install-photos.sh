#!/usr/bin/env bash
# Installs the default photo corpus for `posematch train` and `posematch eval` from Debian's
# wallpaper packages and arranges it as two folders of symbolic links:
#   $DEST/train       plasma-workspace-wallpapers, ukui-wallpapers, sway-backgrounds,
#                     gnome-backgrounds (WebP/SVG files are skipped: not decoded)
#   $DEST/validation  mate-backgrounds — held out: never used for training
# Usage: scripts/install-photos.sh [DEST]     (default DEST: ./data/photos; needs root for apt)
set -euo pipefail
dest="${1:-./data/photos}"
packages=(plasma-workspace-wallpapers ukui-wallpapers sway-backgrounds gnome-backgrounds mate-backgrounds)
sudo=""
if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
missing=()
for p in "${packages[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
mkdir -p "$dest/train" "$dest/validation"
link_package() { # package folder
  local package="$1" folder="$2" n=0
  while IFS= read -r file; do
    case "${file,,}" in
      *.png|*.jpg|*.jpeg) ;;
      *) continue ;;
    esac
    [ -f "$file" ] || continue
    ln -sf "$file" "$folder/${package}--$(echo "$file" | tr '/' '_')"
    n=$((n + 1))
  done < <(dpkg -L "$package")
  echo "$package: $n photos -> $folder"
}
for p in plasma-workspace-wallpapers ukui-wallpapers sway-backgrounds gnome-backgrounds; do
  link_package "$p" "$dest/train"
done
link_package mate-backgrounds "$dest/validation"
