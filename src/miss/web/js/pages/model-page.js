// model.html is one page for two readers: a model's owner (/models/{id}) and whoever
// holds a share link (/s/{token}). The body's class shows that reader's parts
// (data-for="owner" | "guest", see miss.css); the matching page module runs.

import { start as startOwner } from './viewer-page.js';
import { start as startGuest } from './share-page.js';

const guest = location.pathname.startsWith( '/s/' );
document.body.classList.add( guest ? 'guest' : 'owner' );
( guest ? startGuest : startOwner )();
