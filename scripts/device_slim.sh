# Usage: bash scripts/device_slim.sh on|off
# The device tool sends the tracked tree, and the shipped weights make it 111 MB, over the GPU machine's 64 MiB. "on"
# takes prismonet/assets/*_model.safetensors out of the index and ignores them locally (.git/info/exclude), so that a
# device call sends only the code, the priors and what it carries; "off" puts them back. Nothing is deleted: the files
# stay on disk, and "off" restores the index from HEAD. Never commit while it is on.
set -e
cd "$(git rev-parse --show-toplevel)"
pattern='/prismonet/assets/*_model.safetensors'
exclude=$(git rev-parse --git-path info/exclude)
case "$1" in
  on)
    mkdir -p "$(dirname "$exclude")"
    git rm --cached -q prismonet/assets/*_model.safetensors
    grep -qxF "$pattern" "$exclude" 2>/dev/null || echo "$pattern" >> "$exclude"
    git ls-files -z | du -ch --apparent-size --files0-from=- | tail -1 ;;
  off)
    git reset -q -- prismonet/assets
    if [ -f "$exclude" ]; then grep -vxF "$pattern" "$exclude" > "$exclude.tmp" || true; mv "$exclude.tmp" "$exclude"; fi
    git status --short -- prismonet/assets ;;
  *) echo "usage: bash scripts/device_slim.sh on|off" >&2; exit 2 ;;
esac
