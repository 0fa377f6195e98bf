// Login page: name and password to POST /api/auth/login; the server sets the
// session cookie, and the browser goes back where it came from.

import { api } from './api.js';

const $ = ( id ) => document.getElementById( id );

// Only a path on this server: an open redirect would let a phishing link bounce
// through MISS's own login page.
function nextPath() {
	const next = new URLSearchParams( location.search ).get( 'next' ) || '/';
	return next.startsWith( '/' ) && ! next.startsWith( '//' ) ? next : '/';
}

$( 'login' ).addEventListener( 'submit', async ( event ) => {
	event.preventDefault();
	$( 'submit' ).disabled = true;
	$( 'login-error' ).hidden = true;
	try {
		await api.login( $( 'username' ).value.trim(), $( 'password' ).value );
		location.assign( nextPath() );
	} catch ( err ) {
		$( 'login-error' ).textContent = err.message || String( err );
		$( 'login-error' ).hidden = false;
		$( 'password' ).select();
	} finally {
		$( 'submit' ).disabled = false;
	}
} );

document.body.dataset.ready = '1';
