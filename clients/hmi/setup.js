/* The Set-up page's entry: the session's token from the dashboard's sign-in
 * (sessionStorage), then each panel mounted into its section. */

import { hmi, TOKEN_KEY } from "./store.js";
import { whenUnauthorized } from "./api.js";
import { mountMarkerLayout } from "./markers.js";

const signIn = document.getElementById("setup-signin");
hmi.token = sessionStorage.getItem(TOKEN_KEY);
whenUnauthorized(() => { signIn.hidden = false; });
if (hmi.token) mountMarkerLayout(document.getElementById("marker-layout"));
else signIn.hidden = false;
