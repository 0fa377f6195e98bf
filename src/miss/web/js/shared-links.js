// Share links a signed-in colleague opened, by share id -> the link's path (/s/{token}).
// The server keeps no token (only its hash), so it lists what you opened by id
// (GET /api/shared-with-me) and this browser, which had the link, remembers where it was.

const KEY = 'miss.sharedLinks';

function all() {
	try {
		return JSON.parse( localStorage.getItem( KEY ) || '{}' ) || {};
	} catch {
		return {};
	}
}

export function rememberLink( shareId, path ) {
	localStorage.setItem( KEY, JSON.stringify( { ...all(), [ shareId ]: path } ) );
}

// The path of a link this browser opened, or null.
export function rememberedLink( shareId ) {
	const path = all()[ shareId ];
	return typeof path === 'string' && path.startsWith( '/s/' ) ? path : null;
}

// Forget links the server no longer lists (revoked, expired, gone).
export function keepOnly( shareIds ) {
	const known = all();
	const kept = Object.fromEntries( shareIds.filter( ( id ) => id in known ).map( ( id ) => [ id, known[ id ] ] ) );
	localStorage.setItem( KEY, JSON.stringify( kept ) );
}
