// What the page says of each avatar's devices: how many it has (its player's tracker
// set, from the roster) and which of them its newest frame lacked (the server solved
// those from its body model or carried them on), as the desktop viewer's HUD says it.

import { rolesOfBits } from "./protocol.js";

/** The line under an avatar's name: "3 devices", "11 devices — lost: left_foot, hip";
 * "" for an avatar of an older recording (no devices named) that has lost nothing. */
export function deviceText(devices, lostBits) {
  const count = devices.length ? `${devices.length} devices` : "";
  const lost = rolesOfBits(lostBits);
  if (!lost.length) return count;
  return `${count ? `${count} — ` : ""}lost: ${lost.join(", ")}`;
}

/** The HUD's lines, one per avatar that has lost devices now ({name, devices, lost}),
 * "player 2 (11 devices): lost left_foot, hip" (overlay.device_lines of the viewer). */
export function lostLines(avatars) {
  const out = [];
  for (const { name, devices, lost } of avatars) {
    const roles = rolesOfBits(lost);
    if (!roles.length) continue;
    const count = devices.length ? ` (${devices.length} devices)` : "";
    out.push(`${name}${count}: lost ${roles.join(", ")}`);
  }
  return out;
}
