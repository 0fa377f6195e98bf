// Login page: name and password to POST /api/auth/login; the server sets the
// session cookie, and the browser goes back where it came from.

import { api } from '../api.js';

const $ = ( id ) => document.getElementById( id );

// Where to go afterwards is the server's to say: the page sends `next` as it came and
// goes where the login's answer says (a path on this server, or "/"). Judging it here
// as well would be a second rule that could disagree with the first.
function wanted() {
	return new URLSearchParams( location.search ).get( 'next' ) || '/';
}

$( 'login' ).addEventListener( 'submit', async ( event ) => {
	event.preventDefault();
	$( 'submit' ).disabled = true;
	$( 'login-error' ).hidden = true;
	try {
		const answer = await api.login( $( 'username' ).value.trim(), $( 'password' ).value, wanted() );
		location.assign( new URL( answer.next, location.origin ) );
	} catch ( err ) {
		$( 'login-error' ).textContent = err.message || String( err );
		$( 'login-error' ).hidden = false;
		$( 'password' ).select();
	} finally {
		$( 'submit' ).disabled = false;
	}
} );

document.body.dataset.ready = '1';
