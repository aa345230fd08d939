// The waiting page: asks for a place every few seconds and, once in, loads the study page
// (the same address, which now opens the study).

import { postJSON, useParticipantToken } from "./api.js";

const page = document.querySelector("#waiting");
const text = document.querySelector("#place-text");
const tokenData = document.querySelector("#participant-token");
if (tokenData) useParticipantToken(JSON.parse(tokenData.textContent));
let askMs = Number(page.dataset.askSeconds || 3) * 1000;

function describe(place) {
  if (place.ahead === 0) return "You are next in line.";
  return place.ahead === 1 ? "1 person is waiting before you." : `${place.ahead} people are waiting before you.`;
}

async function ask() {
  try {
    const place = await postJSON("/api/participant/place");
    if (place.admitted) {
      text.textContent = "A place is free: opening the study…";
      window.location.reload();
      return;
    }
    const line = describe(place);
    if (text.textContent !== line) text.textContent = line;
    askMs = place.ask_seconds * 1000;
  } catch (error) {
    console.warn("could not ask for a place", error);
  }
  setTimeout(ask, askMs);
}

setTimeout(ask, askMs);
