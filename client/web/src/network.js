// The network worker: the page's websocket lives here, not on the page's main thread,
// which spends whole frames drawing (tens of milliseconds with a software renderer).
// Here a message is stamped and decoded when it arrives, and a Pong's arrival time is
// not a frame late: the clock estimate and "received" mean what they do in Python.

import { Connection } from "./connection.js";

let connection = null;

self.onmessage = ({ data }) => {
  if (data.type === "open" && connection === null) {
    connection = new Connection(data.url, data.room, data.name, data.token,
      (message) => self.postMessage(message));
    connection.open();
  } else if (data.type === "report" && connection !== null) {
    connection.report(data.tCapture, data.tReceived, data.tPresented, data.shown, data.mode);
  } else if (data.type === "leave" && connection !== null) {
    connection.leave();
  }
};
