# Sourced by scripts/ab-*.sh (ROOT, REV_A and REV_B set): checks each revision out into a
# temporary worktree, $TMP/a and $TMP/b, sharing ROOT's build/ (the interface package and the
# fill library cache); both are removed when the calling script exits.
TMP="$(mktemp -d)"
cleanup() {
  for side in a b; do git -C "$ROOT" worktree remove --force "$TMP/$side" 2>/dev/null || true; done
  rm -rf "$TMP"
}
trap cleanup EXIT
for side in a b; do
  rev=$REV_A; [ $side = b ] && rev=$REV_B
  git -C "$ROOT" worktree add -q --detach "$TMP/$side" "$(git -C "$ROOT" rev-parse --verify "$rev^{commit}")"
  mkdir -p "$TMP/$side/build"
  for d in "$ROOT"/build/*; do ln -s "$d" "$TMP/$side/build/"; done
done
